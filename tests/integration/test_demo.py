"""`make demo` as a newcomer meets it: on a machine whose default ports are taken, it
picks others, and everything it says to try works as printed."""

from __future__ import annotations

import contextlib
import os
import re
import shlex
import signal
import socket
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from tests.helpers.labs import shared_cache

pytestmark = [pytest.mark.integration, pytest.mark.timeout(600)]


def occupy(port: int) -> socket.socket | None:
    """Listen on 127.0.0.1:``port`` (None if something else holds it already)."""
    sock = socket.socket()
    try:
        sock.bind(("127.0.0.1", port))
    except OSError:
        sock.close()
        return None
    sock.listen()
    return sock


def test_the_demo_on_busy_ports_and_its_advice_as_printed(cache, tmp_path):
    """With 9090 and 8080 taken, the demo runs on free ports, its trials succeed, and each
    command it prints under "Try" works in a shell that sources its env file."""
    data = tmp_path / "lab-data"
    shared_cache(data, cache)
    held = [occupy(9090), occupy(8080)]
    demo = subprocess.Popen(
        [sys.executable, "-m", "labd", "demo", "--data", str(data), "--sandbox", "bwrap"],
        cwd=tmp_path,
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
        start_new_session=True,
    )
    lines: list[str] = []
    ready = threading.Event()

    def read() -> None:
        assert demo.stdout is not None
        for line in demo.stdout:
            lines.append(line)
            if "The lab keeps running" in line:
                ready.set()
        ready.set()

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    try:
        assert ready.wait(480), "".join(lines)
        text = "".join(lines)
        assert demo.poll() is None, text
        chosen = re.search(
            r"the lab: HTTP http://127\.0\.0\.1:(\d+), rosbridge ws://127\.0\.0\.1:(\d+)", text
        )
        assert chosen, text
        assert {int(chosen[1]), int(chosen[2])}.isdisjoint({9090, 8080})
        assert text.count(": SUCCESS: ") == 2, text
        advice = text.split("Try (in another terminal", 1)[1].split("\n\n", 1)[0]
        commands = [line.strip() for line in advice.splitlines()[1:] if line.strip()]
        assert commands[0].startswith("source ") and len(commands) >= 8, commands
        for command in commands[1:]:
            script = f"{commands[0]} && {command}"
            done = subprocess.run(
                ["bash", "-c", script],
                cwd=tmp_path,
                capture_output=True,
                text=True,
                timeout=300,
                env={k: v for k, v in os.environ.items() if not k.startswith("LABD_")},
                check=False,
            )
            assert done.returncode == 0, (command, done.stdout, done.stderr)
            if " rerun " in command:
                assert "reproduced" in done.stdout, done.stdout
        assert Path(tmp_path / "trial.mcap").stat().st_size > 0
        assert shlex.split(commands[0])[1].endswith("demo/env")
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(demo.pid, signal.SIGINT)
        try:
            demo.wait(60)
        except subprocess.TimeoutExpired:
            os.killpg(demo.pid, signal.SIGKILL)
            demo.wait()
        reader.join(10)
        if demo.stdout is not None:
            demo.stdout.close()
        for sock in held:
            if sock is not None:
                sock.close()
