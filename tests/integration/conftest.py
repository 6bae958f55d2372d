"""Integration tests share the root conftest's fixtures (the sandboxes, the lab's side),
and ``labd serve`` as a service used through the ``labd`` command (``make_served_lab``)."""

from __future__ import annotations

import json
import os
import queue
import re
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest


class ServedLab:
    """A `labd serve` process and the `labd` command pointed at it."""

    def __init__(self, data: Path, cache: Path, *extra: str) -> None:
        self.data = data
        self.cache = cache
        self.extra = list(extra)
        self.process: subprocess.Popen[str] | None = None
        self.server = ""
        self.token = ""

    def start(self) -> None:
        command = [
            sys.executable, "-m", "labd", "--log-level", "INFO", "serve", "--data", str(self.data),
            "--cache", str(self.cache), "--http-port", "0", "--bridge-port", "0",
            "--no-robots", "--workers", "1", "--sandbox", "bwrap",
            "--lease", "3", "--allow-local-repos", *self.extra,
        ]  # fmt: skip
        self.process = subprocess.Popen(
            command,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            start_new_session=True,
        )
        lines: queue.Queue[str] = queue.Queue()
        self.output: list[str] = []

        def read() -> None:
            assert self.process is not None and self.process.stdout is not None
            for line in self.process.stdout:
                self.output.append(line)
                lines.put(line)
            lines.put("")

        self.reader = threading.Thread(target=read, daemon=True)
        self.reader.start()
        deadline = time.monotonic() + 300
        while time.monotonic() < deadline:
            line = lines.get(timeout=max(0.1, deadline - time.monotonic()))
            if not line:
                pytest.fail("labd serve exited:\n" + "".join(self.output))
            found = re.search(r"HTTP API on (http://\S+?)/api", line)
            if found:
                self.server = found.group(1)
                return
        pytest.fail("labd serve did not start:\n" + "".join(self.output))

    def kill(self) -> None:
        assert self.process is not None
        self.process.send_signal(signal.SIGKILL)
        self.process.wait(10)
        self._closed()

    def _closed(self) -> None:
        assert self.process is not None and self.process.stdout is not None
        self.reader.join(30)
        self.process.stdout.close()

    def stop(self) -> None:
        if self.process is not None and self.process.poll() is None:
            self.process.send_signal(signal.SIGTERM)
            try:
                self.process.wait(30)
            except subprocess.TimeoutExpired:
                os.killpg(self.process.pid, signal.SIGKILL)
                self.process.wait(10)
            self._closed()

    def labd(self, *args: str, check: bool = True) -> subprocess.CompletedProcess[str]:
        env = {**os.environ, "LABD_SERVER": self.server, "LABD_TOKEN": self.token}
        try:
            done = subprocess.run(
                [sys.executable, "-m", "labd", *args],
                capture_output=True,
                text=True,
                env=env,
                timeout=300,
                check=False,
            )
        except subprocess.TimeoutExpired as err:  # say what the lab was doing meanwhile
            if self.process is not None and self.process.poll() is None:
                self.process.send_signal(signal.SIGUSR1)  # its threads' stacks, to its log
                time.sleep(2)
            status = subprocess.run(
                [sys.executable, "-m", "labd", "status"],
                capture_output=True, text=True, env=env, timeout=60, check=False,
            )  # fmt: skip
            pytest.fail(
                f"labd {' '.join(args)} did not end within 300 s; it said:\n"
                f"{err.stderr if isinstance(err.stderr, str) else (err.stderr or b'').decode()}\n"
                f"labd status:\n{status.stdout}{status.stderr}\n"
                f"the lab's log, its end:\n{''.join(self.output[-400:])}"
            )
        if check and done.returncode != 0:
            pytest.fail(f"labd {' '.join(args)} exited {done.returncode}:\n{done.stderr}")
        return done

    def json(self, *args: str, code: int = 0) -> object:
        """Run a command with --json; it must exit with ``code`` (1: a trial's fail)."""
        done = self.labd(*args, "--json", check=code == 0)
        assert done.returncode == code, done.stdout + done.stderr
        return json.loads(done.stdout)


@pytest.fixture
def make_served_lab(tmp_path: Path, cache: Path) -> Iterator[Callable[..., ServedLab]]:
    """``labd serve`` processes on ``tmp_path / "data"`` with one bubblewrap worker,
    alice's token set: ``make_served_lab(*extra_args)``, started; each stopped at the end."""
    labs: list[ServedLab] = []

    def make(*extra: str) -> ServedLab:
        lab = ServedLab(tmp_path / "data", cache, *extra)
        user = lab.labd("users", "add", "alice", "--data", str(lab.data), "--json")
        lab.token = json.loads(user.stdout)["token"]
        lab.start()
        labs.append(lab)
        return lab

    yield make
    for lab in labs:
        lab.stop()
