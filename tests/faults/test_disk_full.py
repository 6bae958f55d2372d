"""The lab's disk full while a trial records, and while its record is filed.

A tmpfs of 1 MiB stands for the disk: mounted at the lab's work folder (where trials
record) or at its blob store (where records are filed). A controller publishes 64 KiB
of incompressible data on a topic of its own each tick, so its record outgrows the
disk at a known tick. The trial ends as an ``error`` whose reason says the disk is
full; no partial record is kept, filed or served; and the next trial, a small one,
runs and is filed as if nothing had happened.
"""

from __future__ import annotations

import hashlib
import os
import time
from pathlib import Path

import httpx
import pytest

from repository.index import Index
from scheduler.remote import PROTOCOL, PROTOCOL_HEADER
from tests.helpers.githttp import GitRepo

pytestmark = pytest.mark.integration

DISK = 1024 * 1024
TOML = '[controller]\ncommand = ["python", "c.py", "{ticks}"]\ntask = "icreate-maze"\n'
NOISY = """\
import base64, random, sys
from controllers.client import Lab
with Lab.connect() as lab:
    for tick in range(int(sys.argv[1])):
        noise = base64.b64encode(random.Random(tick).randbytes(48_000)).decode()
        lab.publish("/noise", "std_msgs/msg/String", {"data": noise})
        lab.step()
print("stepped", sys.argv[1])
"""


def repo(tmp_path: Path, name: str, ticks: int) -> Path:
    files = {"lab.toml": TOML.format(ticks=ticks), "c.py": NOISY}
    return GitRepo.create(tmp_path / name, files).path


def run_big_then_small(lab, tmp_path: Path, big_ticks: int) -> tuple[dict, dict]:
    lab.token = lab.add_user("alice")
    lab.start()
    big = lab.submit(repo(tmp_path, "big", big_ticks))
    small = lab.submit(repo(tmp_path, "small", 3))
    return tuple(lab.wait_ended([big["id"], small["id"]], 120))


def check_the_small_one(lab, small: dict) -> None:
    """The next trial is untouched: it ran, and its record is filed whole."""
    assert small["outcome"] == "fail", small
    assert small["reason"].startswith("the controller exited with 0 at tick 3"), small
    record = httpx.get(f"{lab.server}/api/trials/{small['id']}/data.mcap", timeout=30)
    assert record.status_code == 200
    assert "sha256:" + hashlib.sha256(record.content).hexdigest() == small["mcap"]["digest"]


@pytest.mark.timeout(120)
def test_disk_full_while_recording(served, small_disk, tmp_path: Path):
    """The work folder fills up mid-trial: the trial is an error saying the lab's disk is
    full, its partial record is deleted and never filed, and the next trial runs."""
    data = tmp_path / "data"
    work = small_disk(data / "work", DISK)
    lab = served(
        "--no-robots", "--workers", "1", "--sandbox", "bwrap", "--allow-local-repos", data=data
    )
    big, small = run_big_then_small(lab, tmp_path, 40)  # 2.5 MiB of noise
    assert (big["status"], big["outcome"]) == ("finished", "error"), big
    assert big["reason"].startswith(
        "the lab's disk is full: the trial's record could not be written (No space left on device: "
    ), big["reason"]
    assert big["reason"].endswith("trial.mcap); the partial record was deleted"), big["reason"]
    assert big["mcap"] is None and big["data_digest"] is None
    refused = httpx.get(f"{lab.server}/api/trials/{big['id']}/data.mcap", timeout=30)
    assert refused.status_code == 404 and "has no record" in refused.json()["error"]
    stdout = httpx.get(big["logs"]["stdout"], timeout=30).text
    assert stdout == "stepped 40\n"  # the robot went on stepping: the controller ran to its end
    assert "internal error" not in lab.log, lab.log
    check_the_small_one(lab, small)
    # nothing left behind on the full disk, once the small one's replay is made beside
    deadline = time.monotonic() + 60
    while os.listdir(work) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert os.listdir(work) == []


@pytest.mark.timeout(120)
def test_disk_full_while_filing(served, small_disk, tmp_path: Path):
    """The blob store fills up while a record is stored: the trial is an error saying the
    lab's disk is full, no part of its record is in the store, a worker's upload is
    refused with 507, and the next trial is filed."""
    blobs = small_disk(tmp_path / "blobs", DISK)
    lab = served(
        "--no-robots", "--workers", "1", "--sandbox", "bwrap", "--blobs", str(blobs),
        "--allow-local-repos",
    )  # fmt: skip
    big, small = run_big_then_small(lab, tmp_path, 24)  # 1.5 MiB of noise
    assert (big["status"], big["outcome"]) == ("finished", "error"), big
    assert big["reason"] == (
        "the lab's disk is full: the archive could not store the record (No space left on device)"
    ), big["reason"]
    assert big["mcap"] is None
    check_the_small_one(lab, small)
    logs = [httpx.get(small["logs"][s], timeout=30).content for s in ("stdout", "stderr")]
    # what is made of its record beside it (summary, replay verdict, video) is filed after
    # the trial ends: wait for the replay's verdict, then take the rest from the index
    verdict = f"{lab.server}/api/trials/{small['id']}/replay"
    deadline = time.monotonic() + 60
    while httpx.get(verdict, timeout=30).status_code == 404 and time.monotonic() < deadline:
        time.sleep(0.2)
    derived = Index.open(f"sqlite:///{lab.data / 'index.sqlite'}").derived(small["id"])
    assert {"summary.json", "replay.json"} <= set(derived), derived
    files = [p for p in (blobs / "sha256").rglob("*") if p.is_file()]
    kept = ["sha256:" + hashlib.sha256(b).hexdigest() for b in logs]
    assert sorted(f"sha256:{p.name}" for p in files) == sorted(  # the small trial's alone
        {small["mcap"]["digest"], *kept, *(item.digest for item in derived.values())}
    )
    for path in files:  # and each is whole: its bytes hash to its name
        assert hashlib.sha256(path.read_bytes()).hexdigest() == path.name
    assert not list((blobs / "tmp").iterdir())  # no half-written upload left
    worker = lab.add_user("w1", "--worker")
    body = os.urandom(2 * DISK)
    digest = "sha256:" + hashlib.sha256(body).hexdigest()
    upload = httpx.put(
        f"{lab.server}/api/blobs/{digest}",
        content=body,
        headers={"Authorization": f"Bearer {worker}", PROTOCOL_HEADER: str(PROTOCOL)},
        timeout=60,
    )
    assert upload.status_code == 507, upload.text
    assert upload.json()["error"].startswith("the lab's disk is full: the lab could not store")
    assert not (blobs / "sha256" / digest[7:9] / digest[7:]).exists()
