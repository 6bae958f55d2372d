"""The ``labd`` command, run as a user runs it."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
from pathlib import Path

import orjson
import pytest
from websockets.sync.client import connect

from scheduler.fetch import FetchPolicy
from tests.helpers.githttp import GitRepo
from tests.helpers.labs import lab_config, running, shared_cache

pytestmark = pytest.mark.integration
LAB_TOML = '[controller]\ncommand = ["python", "c.py"]\ntask = "icreate-maze"\n'


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


def test_a_relative_repository_path_is_the_caller_s(tmp_path):
    """``labd submit maze`` and ``labd evaluate maze``, run in the user's folder, send the
    folder the user means (not one under the lab's folder), and ``--repo maze`` lists what
    they queued; a URL goes as it is."""
    user = tmp_path / "user"
    made = GitRepo.create(user / "maze", {"lab.toml": LAB_TOML, "c.py": "pass\n"}).path
    fetch = FetchPolicy(schemes=frozenset({"file"}))
    with running(lab_config(tmp_path / "data", robots=(), service={"fetch": fetch})) as lab:
        assert not (Path.cwd() / "maze").exists()  # the lab's own folder has none
        env = {
            **os.environ,
            "LABD_SERVER": lab.http_url(),
            "LABD_TOKEN": lab.lab.service.index.add_user("alice", max_daily=500),
        }

        def labd(*args: str) -> subprocess.CompletedProcess[str]:
            command = [sys.executable, "-m", "labd", *args, "--json"]
            return subprocess.run(
                command, cwd=user, env=env, capture_output=True, text=True, timeout=60, check=False
            )

        submitted = labd("submit", "maze")
        assert submitted.returncode == 0, submitted.stdout + submitted.stderr
        assert json.loads(submitted.stdout)["repository"] == str(made.resolve())
        evaluated = labd("evaluate", "./maze/")
        assert evaluated.returncode == 0, evaluated.stdout + evaluated.stderr
        assert json.loads(evaluated.stdout)["repository"] == str(made.resolve())
        listed = json.loads(labd("trials", "--repo", "maze", "--limit", "30").stdout)["trials"]
        assert len(listed) == 21
        listed = json.loads(labd("evaluations", "--repo", "maze").stdout)["evaluations"]
        assert len(listed) == 1
        url = labd("submit", GitRepo(made).url)
        assert json.loads(url.stdout)["repository"] == str(made.resolve())
