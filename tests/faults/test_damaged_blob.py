"""A blob of the archive damaged on disk: never served, never filed again as it is.

The archive names each blob by the sha256 of its bytes and checks them whenever it reads
them. A record damaged on disk (a flipped byte, a truncated log) is refused with a 500
that says so, by every route and by `labd download`; an upload of bytes that do not hash
to their name is refused, so nothing can overwrite it with other bytes. A rerun writes a
new record: one that reproduced brings the same bytes, which heal the damaged blob; one
that did not compares against the damaged original, and says so, without copying it.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

import httpx
import pytest

from scheduler.remote import PROTOCOL, PROTOCOL_HEADER
from tests.faults.slow import controller
from tests.helpers.githttp import GitRepo

pytestmark = pytest.mark.integration

RANDOM = """\
import random
from controllers.client import Lab
with Lab.connect() as lab:
    for _ in range(3):
        lab.publish("/cmd_vel", "geometry_msgs/msg/Twist", {"angular": {"z": random.random()}})
        lab.step()
"""


def blob_path(lab, digest: str) -> Path:
    return lab.data / "blobs" / "sha256" / digest[7:9] / digest[7:]


def damage(path: Path, truncate: bool = False) -> bytes:
    """Flip a byte of the file (or cut it short), as a failing disk would; its new bytes."""
    os.chmod(path, 0o644)
    data = bytearray(path.read_bytes())
    if truncate:
        data = data[: len(data) // 2]
    else:
        data[len(data) // 2] ^= 0x01
    path.write_bytes(bytes(data))
    return bytes(data)


def sha(data: bytes) -> str:
    return "sha256:" + hashlib.sha256(data).hexdigest()


@pytest.mark.timeout(150)
def test_a_damaged_blob_is_never_served_nor_filed_again(served, tmp_path: Path):
    """Damaged records and logs get a 500 naming the damage on every route; a worker's
    upload of other bytes under the name is refused; a rerun that reproduced heals the
    blob, and one that did not says the original's record is damaged."""
    lab = served("--no-robots", "--workers", "1", "--sandbox", "bwrap", "--allow-local-repos")
    lab.token = lab.add_user("alice")
    worker = lab.add_user("w1", "--worker")
    lab.start()
    talks = {**controller(3), "c.py": "print('a line for the log')\n" + controller(3)["c.py"]}
    steady = lab.submit(GitRepo.create(tmp_path / "steady", talks).path)
    wobbly = lab.submit(GitRepo.create(tmp_path / "wobbly", {**controller(3), "c.py": RANDOM}).path)
    steady, wobbly = lab.wait_ended([steady["id"], wobbly["id"]], 120)
    digest = steady["mcap"]["digest"]
    damaged = damage(blob_path(lab, digest))
    stdout = sha(httpx.get(steady["logs"]["stdout"], timeout=30).content)
    damage(blob_path(lab, stdout), truncate=True)

    for url in (
        f"/api/trials/{steady['id']}/data.mcap",
        f"/api/blobs/{digest}",
        f"/api/trials/{steady['id']}/logs/stdout",
    ):
        answer = httpx.get(lab.server + url, timeout=30)
        assert answer.status_code == 500, (url, answer.status_code)
        assert answer.headers["content-type"] == "application/json"
        assert "damaged" in answer.json()["error"], answer.text
    out = tmp_path / "download.mcap"
    done = lab.labd("download", str(steady["id"]), "-o", str(out), check=False)
    assert done.returncode == 2 and "damaged" in done.stderr, done.stderr
    assert not out.exists() and not list(tmp_path.glob("download.mcap*"))

    upload = httpx.put(  # a worker offering other bytes under the damaged blob's name
        f"{lab.server}/api/blobs/{digest}",
        content=damaged,
        headers={"Authorization": f"Bearer {worker}", PROTOCOL_HEADER: str(PROTOCOL)},
        timeout=30,
    )
    assert upload.status_code == 422, upload.text
    assert upload.json()["error"] == f"the body hashes to {sha(damaged)}, not {digest}"
    assert blob_path(lab, digest).read_bytes() == damaged  # refused: nothing was written

    again = lab.labd("rerun", str(steady["id"]), "--wait", "--json", check=False)
    assert again.returncode == 0, again.stdout + again.stderr  # 0: reproduced
    rerun = lab.trial(int(again.stdout.split('"id": ')[1].split(",")[0]))
    assert (rerun["rerun_of"], rerun["reproduced"]) == (steady["id"], True), rerun
    assert rerun["id"] != steady["id"] and rerun["mcap"]["digest"] == digest
    for trial in (rerun, steady):  # the rerun's record is whole, and it healed the original's
        record = httpx.get(f"{lab.server}/api/trials/{trial['id']}/data.mcap", timeout=30)
        assert record.status_code == 200 and sha(record.content) == digest
    assert f"blob {digest} was damaged; the same bytes, stored again, replace it" in lab.log

    damage(blob_path(lab, wobbly["mcap"]["digest"]))
    differs = lab.labd("rerun", str(wobbly["id"]), "--wait", "--json", check=False)
    assert differs.returncode == 5, differs.stdout + differs.stderr  # 5: did not reproduce
    [other] = [t for t in lab.get(f"/api/trials?rerun_of={wobbly['id']}")["trials"]]
    other = lab.trial(other["id"])
    assert other["reproduced"] is False
    assert other["divergence"].startswith("the original's record: "), other["divergence"]
    assert "damaged" in other["divergence"], other["divergence"]
    record = httpx.get(f"{lab.server}/api/trials/{other['id']}/data.mcap", timeout=30)
    assert record.status_code == 200 and sha(record.content) == other["mcap"]["digest"]
    assert other["mcap"]["digest"] != wobbly["mcap"]["digest"]
