"""A worker on another machine (`labd worker --server`) lost in the middle of a trial.

Killed (SIGKILL), its lease runs out and the queue gives the trial to another worker,
which runs it again and files it. Frozen (SIGSTOP, a machine that hangs) and then
thawed after another worker has filed the trial, it learns at its next heartbeat that
the trial is no longer its own, stops, and its late filing is refused: the record is
the other worker's, filed once.
"""

from __future__ import annotations

import hashlib
import signal
import socket
import subprocess
import sys
from pathlib import Path

import httpx
import psutil
import pytest

from tests.faults.conftest import gone, wait_for
from tests.faults.slow import controller
from tests.helpers.githttp import GitRepo

pytestmark = pytest.mark.integration
LEASE = "3"


class RemoteWorker:
    """`labd worker --server URL` in a process of its own, with its own data folder."""

    def __init__(self, lab, token: str, data: Path, cache: Path) -> None:
        data.mkdir()
        (data / "cache").symlink_to(cache)  # the runtime, built once for the session
        self.data = data
        self.process = subprocess.Popen(
            [sys.executable, "-m", "labd", "--log-level", "INFO", "worker", "--server", lab.server, "--token", token,
             "--sandbox", "bwrap", "--data", str(data), "--poll", "0.2", "--heartbeat", "1",
             "--allow-local-repos"],
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True,
        )  # fmt: skip

    def record(self, trial_id: int, attempt: int) -> Path:
        return self.data / "work" / f"trial-{trial_id}-{attempt}" / "trial.mcap"

    def stop(self) -> str:
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGCONT)
            self.process.send_signal(signal.SIGTERM)
            try:
                self.process.wait(30)
            except subprocess.TimeoutExpired:
                self.process.kill()
        output, _ = self.process.communicate(timeout=30)
        return output


@pytest.mark.parametrize("lost", ["killed", "frozen"])
@pytest.mark.timeout(300)
def test_a_remote_worker_lost_mid_trial(served, cache: Path, tmp_path: Path, lost: str):
    """The trial of a worker killed or frozen mid-trial is requeued when its lease runs out,
    run by another worker and filed once; a frozen worker that wakes files nothing."""
    lab = served("--no-robots", "--workers", "0", "--lease", LEASE, "--allow-local-repos")
    lab.token = lab.add_user("alice")
    worker_token = lab.add_user("w1", "--worker")
    lab.start()
    first = RemoteWorker(lab, worker_token, tmp_path / "first", cache)
    workers = [first]
    try:
        trial = lab.submit(GitRepo.create(tmp_path / "slow", controller(40, 0.1)).path)
        wait_for("the first worker to record", lambda: first.record(trial["id"], 1).exists(), 90)
        row = lab.trial(trial["id"])
        assert (row["status"], row["attempts"]) == ("running", 1)
        if lost == "killed":
            sandboxes = psutil.Process(first.process.pid).children(recursive=True)
            first.process.send_signal(signal.SIGKILL)
            first.process.wait(10)
            gone(sandboxes)
        else:
            first.process.send_signal(signal.SIGSTOP)
        second = RemoteWorker(lab, worker_token, tmp_path / "second", cache)
        workers.append(second)
        [done] = lab.wait_ended([trial["id"]], 150)
        assert done["outcome"] == "fail", done
        assert done["reason"].startswith("the controller exited with 0 at tick 40"), done
        assert done["attempts"] == 2
        assert done["worker"] == f"w1@{socket.gethostname()}:{second.process.pid}/remote-1"
        assert f"lease of worker w1@{socket.gethostname()}:{first.process.pid}/" in lab.log
        if lost == "frozen":
            first.process.send_signal(signal.SIGCONT)
            wait_for(
                "the thawed worker's filing to be refused",
                lambda: f"finished trial {trial['id']} after losing it; dropped" in lab.log,
                120,
                detail=lambda: f"the lab:\n{lab.log}\nthe thawed worker:\n{first.stop()}",
            )
        assert lab.trial(trial["id"]) == done  # filed once: the second worker's record
        record = httpx.get(f"{lab.server}/api/trials/{trial['id']}/data.mcap", timeout=30)
        assert "sha256:" + hashlib.sha256(record.content).hexdigest() == done["mcap"]["digest"]
    finally:
        outputs = [w.stop() for w in workers]
    assert second.process.returncode == 0, outputs
