"""`labd serve` SIGKILLed in each stage of a trial: preparing, running, filing.

Each stage is held by a real slow condition, not a hook: a package index that does not
answer yet (preparing: installing the requirements), a controller that steps slowly
(running), an S3 server that is stopped (filing: uploading the record). The lab is
killed there, its sandboxes die with it, and a new `labd serve` on the same data folder
requeues the trial at once. Every submission then ends exactly once: the killed trial
on its second attempt, the one queued behind it on its first, no trial made or lost,
and each record downloads intact.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import httpx
import pytest

from tests.faults.conftest import gone, wait_for
from tests.faults.slow import PackageIndex, S3Server, controller
from tests.helpers.githttp import GitRepo

pytestmark = pytest.mark.integration

# -- the scenario ----------------------------------------------------------------------------


def kill_and_restart(lab, trial_id: int, stage: str) -> None:
    """SIGKILL the lab while the trial is in ``stage``; its sandboxes die; start it again."""
    assert lab.stage(trial_id) == stage
    assert lab.trial(trial_id)["status"] == "running"
    gone(lab.kill())
    lab.start()
    assert f"requeued trials a killed labd left running: [{trial_id}]" in lab.log, lab.log


def check_ended_once(lab, submitted: list[int], target: dict, queued: dict) -> None:
    """No trial made or lost; the killed one ran twice, the queued one once; records intact."""
    listed = lab.get("/api/trials?limit=500")["trials"]
    assert sorted(t["id"] for t in listed) == sorted(submitted)
    assert (target["attempts"], queued["attempts"]) == (2, 1)
    for row in (target, queued):
        assert row["status"] == "finished", row
        record = httpx.get(f"{lab.server}/api/trials/{row['id']}/data.mcap", timeout=30)
        assert record.status_code == 200
        assert "sha256:" + hashlib.sha256(record.content).hexdigest() == row["mcap"]["digest"]


@pytest.mark.timeout(180)
def test_sigkill_while_preparing(served, held_package_index: PackageIndex, tmp_path: Path):
    """Killed while the requirements install (the index has not answered): the trial is
    requeued, installs on its second attempt, runs and is filed once."""
    lab = served("--no-robots", "--workers", "1", "--sandbox", "bwrap", "--lease", "3",
                 "--allow-local-repos", env={"PIP_INDEX_URL": held_package_index.url})  # fmt: skip
    lab.token = lab.add_user("alice")
    lab.start()
    target = lab.submit(GitRepo.create(tmp_path / "t", controller(3, requirements=True)).path)
    queued = lab.submit(GitRepo.create(tmp_path / "q", controller(3)).path)
    assert held_package_index.asked.wait(60), lab.log
    kill_and_restart(lab, target["id"], "preparing")
    held_package_index.release.set()
    rows = lab.wait_ended([target["id"], queued["id"]], 120)
    for row in rows:
        assert row["reason"].startswith("the controller exited with 0 at tick 3"), row["reason"]
    check_ended_once(lab, [target["id"], queued["id"]], *rows)
    stdout = httpx.get(rows[0]["logs"]["stdout"], timeout=30).text
    assert stdout == "tinypkg 7\n"


@pytest.mark.timeout(180)
def test_sigkill_while_running(served, tmp_path: Path):
    """Killed while the controller steps: the trial is requeued, runs again from the start
    and is filed once, with the same data as an uninterrupted run."""
    lab = served("--no-robots", "--workers", "1", "--sandbox", "bwrap", "--lease", "3",
                 "--allow-local-repos")  # fmt: skip
    lab.token = lab.add_user("alice")
    lab.start()
    target = lab.submit(GitRepo.create(tmp_path / "t", controller(40, 0.1)).path)
    queued = lab.submit(GitRepo.create(tmp_path / "q", controller(3)).path)
    record = lab.data / "work" / f"trial-{target['id']}-1" / "trial.mcap"
    wait_for("the first attempt to record", record.exists, 60, every=0.05)
    kill_and_restart(lab, target["id"], "running")
    rows = lab.wait_ended([target["id"], queued["id"]], 120)
    assert rows[0]["reason"].startswith("the controller exited with 0 at tick 40"), rows[0]
    check_ended_once(lab, [target["id"], queued["id"]], *rows)
    again = lab.submit(Path(rows[0]["repository"]))  # the same trial, never interrupted
    [same] = lab.wait_ended([again["id"]], 120)
    assert same["data_digest"] == rows[0]["data_digest"]


@pytest.mark.timeout(180)
def test_sigkill_while_filing(served, s3: S3Server, tmp_path: Path):
    """Killed while the record uploads to a stopped S3 server: the trial is requeued, and
    once the store answers again it runs and is filed once; the bucket holds its record."""
    lab = served("--no-robots", "--workers", "1", "--sandbox", "bwrap", "--lease", "3",
                 "--allow-local-repos", "--blobs", "s3://lab-archive/records", "--blobs-option",
                 f"endpoint_url={s3.url}")  # fmt: skip
    lab.token = lab.add_user("alice")
    lab.start()
    s3.pause()  # nothing touches the store before filing
    target = lab.submit(GitRepo.create(tmp_path / "t", controller(3)).path)
    queued = lab.submit(GitRepo.create(tmp_path / "q", controller(5)).path)
    wait_for("the trial to be filing", lambda: lab.stage(target["id"]) == "filing", 60)
    kill_and_restart(lab, target["id"], "filing")
    s3.resume()
    rows = lab.wait_ended([target["id"], queued["id"]], 120)
    assert rows[0]["reason"].startswith("the controller exited with 0 at tick 3"), rows[0]
    assert rows[1]["reason"].startswith("the controller exited with 0 at tick 5"), rows[1]
    check_ended_once(lab, [target["id"], queued["id"]], *rows)
    s3.fs.invalidate_cache()
    for row in rows:
        digest = row["mcap"]["digest"]
        assert s3.fs.exists(f"lab-archive/records/sha256/{digest[7:9]}/{digest[7:]}")
