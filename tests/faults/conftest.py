"""What the fault suite shares: a real `labd serve` process to kill, and the trial fixtures.

``Served`` runs ``labd serve`` as its own process group on loopback and free ports,
reads where it listens from its output, and can SIGKILL it and start it again on the
same data folder, as an operator's machine would after a crash.
"""

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
from typing import Any

import httpx
import psutil
import pytest

from tests.faults.slow import PackageIndex, S3Server

__all__ = [
    "Served",
    "gone",
    "held_package_index",
    "make_bare_lab",
    "s3",
    "served",
    "small_disk",
    "wait_for",
]

START = 120.0  # seconds `labd serve` may take to listen (the first runtime build is cached)


def wait_for(
    what: str,
    predicate: Callable[[], Any],
    timeout: float,
    every: float = 0.1,
    detail: Callable[[], str] | None = None,
) -> Any:
    """Poll ``predicate`` until it returns something true, for at most ``timeout`` seconds;
    ``detail`` says more when it does not."""
    deadline = time.monotonic() + timeout
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            more = f"\n{detail()}" if detail else ""
            pytest.fail(f"{what}: not within {timeout:g} s{more}")
        time.sleep(every)


class Served:
    """A `labd serve` process on the data folder ``data``, started with ``args``."""

    def __init__(
        self, data: Path, cache: Path, *args: str, env: dict[str, str] | None = None
    ) -> None:
        self.data = data
        self.cache = cache
        self.args = list(args)
        self.env = {**os.environ, **(env or {})}
        self.process: subprocess.Popen[str] | None = None
        self.output: list[str] = []
        self.bridge = ""  # ws://127.0.0.1:PORT
        self.server = ""  # http://127.0.0.1:PORT, when it runs the service
        self.token = ""

    def start(self) -> Served:
        args = list(self.args)
        top: list[str] = []  # `labd`'s own option goes before the command
        if "--log-level" in args:
            at = args.index("--log-level")
            top, args[at : at + 2] = args[at : at + 2], []
        command = [
            sys.executable, "-m", "labd", *top, "serve", "--data", str(self.data),
            "--cache", str(self.cache), "--http-port", "0", "--bridge-port", "0",
            "--videos", "asked", *args,
        ]  # fmt: skip
        self.output = []
        self.process = subprocess.Popen(
            command,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            start_new_session=True,
            env=self.env,
        )
        lines: queue.Queue[str] = queue.Queue()

        def read() -> None:
            assert self.process is not None and self.process.stdout is not None
            for line in self.process.stdout:
                self.output.append(line)
                lines.put(line)
            lines.put("")

        self._reader = threading.Thread(target=read, daemon=True)
        self._reader.start()
        service = "--no-service" not in self.args
        deadline = time.monotonic() + START
        while time.monotonic() < deadline:
            try:
                line = lines.get(timeout=max(0.1, deadline - time.monotonic()))
            except queue.Empty:
                break
            if not line:
                pytest.fail("labd serve exited:\n" + self.log)
            if found := re.search(r"rosbridge v2 on (wss?://\S+)", line):
                self.bridge = found.group(1).rstrip("/")
            if found := re.search(r"HTTP API on (https?://\S+?)/api", line):
                self.server = found.group(1)
            if (service and line.startswith("  workers:")) or (
                not service and "serves the first of these" in line
            ):
                return self
        pytest.fail("labd serve did not start:\n" + self.log)

    @property
    def log(self) -> str:
        return "".join(self.output)

    @property
    def pid(self) -> int:
        assert self.process is not None
        return self.process.pid

    def rss(self) -> int:
        """The server's resident memory, in bytes."""
        return int(psutil.Process(self.pid).memory_info().rss)

    def kill(self) -> list[psutil.Process]:
        """SIGKILL, as a crash or the OOM killer would; the processes it had started."""
        assert self.process is not None
        children = psutil.Process(self.pid).children(recursive=True)
        self.process.send_signal(signal.SIGKILL)
        self.process.wait(10)
        self._closed()
        return children

    def _closed(self) -> None:
        assert self.process is not None and self.process.stdout is not None
        self._reader.join(30)
        self.process.stdout.close()

    def stop(self) -> None:
        if self.process is None or self.process.poll() is not None:
            return
        self.process.send_signal(signal.SIGTERM)
        try:
            self.process.wait(60)
        except subprocess.TimeoutExpired:
            os.killpg(self.process.pid, signal.SIGKILL)
            self.process.wait(10)
        self._closed()

    # -- talking to it -------------------------------------------------------------------

    def labd(self, *args: str, check: bool = True) -> subprocess.CompletedProcess[str]:
        """The `labd` command pointed at this lab."""
        env = {**os.environ, "LABD_SERVER": self.server, "LABD_TOKEN": self.token}
        done = subprocess.run(
            [sys.executable, "-m", "labd", *args],
            capture_output=True,
            text=True,
            env=env,
            timeout=120,
            check=False,
        )
        if check and done.returncode != 0:
            pytest.fail(f"labd {' '.join(args)} exited {done.returncode}:\n{done.stderr}")
        return done

    def add_user(self, name: str, *options: str) -> str:
        """A user of this lab's archive (``--worker`` for a worker); their token."""
        where = ["--data", str(self.data)]
        if "--database" in self.args:
            where += ["--database", self.args[self.args.index("--database") + 1]]
        made = self.labd("users", "add", name, *where, "--json", *options)
        return str(json.loads(made.stdout)["token"])

    def get(self, path: str) -> Any:
        answer = httpx.get(f"{self.server}{path}", timeout=30)
        assert answer.status_code == 200, (path, answer.status_code, answer.text)
        return answer.json()

    def submit(self, repo: Path, **fields: Any) -> dict[str, Any]:
        body = {"repository": str(repo), "task": "icreate-maze", **fields}
        answer = httpx.post(
            f"{self.server}/api/trials",
            json=body,
            headers={"Authorization": f"Bearer {self.token}"},
            timeout=60,
        )
        assert answer.status_code == 201, answer.text
        trial: dict[str, Any] = answer.json()
        return trial

    def trial(self, trial_id: int) -> dict[str, Any]:
        trial: dict[str, Any] = self.get(f"/api/trials/{trial_id}")
        return trial

    def stage(self, trial_id: int) -> str | None:
        """The stage a local worker has the trial in (preparing, running, filing), or None."""
        for row in self.get("/api/status")["running"]:
            if row["trial"] == trial_id:
                return str(row["stage"]) if row["stage"] else None
        return None

    def wait_ended(self, ids: list[int], timeout: float) -> list[dict[str, Any]]:
        def ended() -> list[dict[str, Any]] | None:
            rows = [self.trial(i) for i in ids]
            return rows if all(r["status"] in ("finished", "cancelled") for r in rows) else None

        rows: list[dict[str, Any]] = wait_for(f"trials {ids} to end", ended, timeout, every=0.25)
        return rows


def gone(processes: list[psutil.Process], timeout: float = 20) -> None:
    """Wait until each of ``processes`` has ended (a zombie has ended too); else fail,
    naming those still there."""

    def ended(p: psutil.Process) -> bool:
        try:
            return not p.is_running() or p.status() == psutil.STATUS_ZOMBIE
        except psutil.NoSuchProcess:
            return True

    def alive() -> list[psutil.Process]:
        return [p for p in processes if not ended(p)]

    wait_for(
        "the processes to end",
        lambda: not alive(),
        timeout,
        detail=lambda: "still there: " + ", ".join(f"{p.pid} {p.name()}" for p in alive()),
    )


@pytest.fixture
def held_package_index() -> Iterator[PackageIndex]:
    """A package index whose page of tinypkg waits until its ``release`` is set."""
    server = PackageIndex()
    yield server
    server.release.set()
    server.shutdown()
    server.server_close()


@pytest.fixture
def s3(monkeypatch: pytest.MonkeyPatch) -> Iterator[S3Server]:
    """An S3 server (moto) that can be frozen, with a bucket ``lab-archive``; the lab
    finds its keys in the environment."""
    monkeypatch.setenv("AWS_ACCESS_KEY_ID", "testing")
    monkeypatch.setenv("AWS_SECRET_ACCESS_KEY", "testing")
    server = S3Server()
    yield server
    server.close()


@pytest.fixture
def small_disk() -> Iterator[Callable[[Path, int], Path]]:
    """Mount a tmpfs of ``size`` bytes at a folder: a disk that fills up (needs root)."""
    if os.geteuid() != 0:
        if os.environ.get("CI"):
            pytest.fail("a small filesystem needs root to mount")
        pytest.skip("a small filesystem needs root to mount")
    mounted: list[Path] = []

    def mount(folder: Path, size: int) -> Path:
        folder.mkdir(parents=True, exist_ok=True)
        subprocess.run(
            ["mount", "-t", "tmpfs", "-o", f"size={size},mode=0755", "tmpfs", str(folder)],
            check=True,
        )
        mounted.append(folder)
        return folder

    yield mount
    for folder in reversed(mounted):
        subprocess.run(["umount", "--lazy", str(folder)], check=True)


@pytest.fixture
def served(tmp_path: Path, cache: Path) -> Iterator[Callable[..., Served]]:
    """Labs to start: ``served(*args, data=None, env=None)``; each is stopped at the end."""
    labs: list[Served] = []

    def make(*args: str, data: Path | None = None, env: dict[str, str] | None = None) -> Served:
        lab = Served(data or tmp_path / "data", cache, *args, env=env)
        labs.append(lab)
        return lab

    yield make
    for lab in labs:
        lab.stop()


BARE = ("--no-robots", "--workers", "0")


@pytest.fixture
def make_bare_lab(tmp_path: Path) -> Iterator[Callable[..., Served]]:
    """Labs to start with no robot and no worker, each on a data folder and a git cache
    of its own (what is measured is theirs alone), mallory's token set:
    ``make_bare_lab(*args, env=None)``; each is stopped at the end."""
    labs: list[Served] = []

    def make(*args: str, env: dict[str, str] | None = None) -> Served:
        n = len(labs)
        served = Served(tmp_path / f"data-{n}", tmp_path / f"cache-{n}", *BARE, *args, env=env)
        labs.append(served)
        served.start()
        served.token = served.add_user("mallory")
        return served

    yield make
    for served in labs:
        served.stop()
