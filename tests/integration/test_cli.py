"""The ``labd`` command, run as a user runs it."""

from __future__ import annotations

import re
import signal
import subprocess
import sys

import orjson
import pytest
from websockets.sync.client import connect

from tests.helpers.labs import shared_cache

pytestmark = pytest.mark.integration


def test_serve_starts_answers_and_stops_on_sigterm(tmp_path, cache):
    """labd serve prints its URL, answers rosapi there, and exits cleanly on SIGTERM."""
    shared_cache(tmp_path, cache)  # its workers find the session's runtime, not a cold build
    with subprocess.Popen(
        [
            sys.executable,
            "-m",
            "labd",
            "serve",
            "--bridge-port",
            "0",
            "--http-port",
            "0",
            "--data",
            str(tmp_path),
            "--no-robots",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
    ) as proc:
        _check_serve(proc)


def _check_serve(proc: subprocess.Popen[str]) -> None:
    try:
        assert proc.stdout is not None
        first = proc.stdout.readline()
        match = re.search(r"rosbridge v2 on (ws://127\.0\.0\.1:\d+)", first)
        assert match, first
        with connect(match.group(1)) as ws:
            ws.send(
                orjson.dumps(
                    {"op": "call_service", "id": 1, "service": "/rosapi/get_ros_version"}
                ).decode()
            )
            assert orjson.loads(ws.recv(timeout=10))["values"] == {"version": 2, "distro": "jazzy"}
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=10) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_tls_flags_go_together():
    """--tls-cert without --tls-key is refused with a message saying so."""
    result = subprocess.run(
        [sys.executable, "-m", "labd", "serve", "--tls-cert", "x.pem"],
        check=False,
        capture_output=True,
        text=True,
        timeout=30,
    )
    assert result.returncode != 0 and "--tls-cert and --tls-key go together" in result.stderr
