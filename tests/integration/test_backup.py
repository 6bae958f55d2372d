"""`labd backup` of a lab serving a running trial, and `labd restore` into a new folder
(and a new database), on SQLite and on PostgreSQL.

A real `labd serve` with a worker runs a controller that steps until the test lets it
go, so the backup is taken while its trial runs, whatever the machine's speed; the
backup restores into a fresh lab whose `labd serve` lists the same trials as the lab did
then, serves the same bytes, and whose every record `labd verify` accepts. A second
backup into the same folder copies only the blobs it lacks; a restore into a lab that
holds trials is refused.
"""

from __future__ import annotations

import hashlib
import json
import subprocess
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

from labd.hosted import HostedRepos
from tests.conftest import postgres_databases
from tests.faults.conftest import Served, wait_for
from tests.faults.slow import Held, controller
from tests.helpers.githttp import GitRepo
from tests.helpers.timing import SECOND

pytestmark = pytest.mark.integration

WHEN = 1_700_000_000


def labd(*args: str) -> subprocess.CompletedProcess[str]:
    """``labd backup ...`` or ``labd restore ...``, in a process of its own."""
    return subprocess.run(
        [sys.executable, "-m", "labd", *args],
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )


def ok(*args: str) -> dict[str, Any]:
    """The command with ``--json``; it must succeed."""
    done = labd(*args, "--json")
    assert done.returncode == 0, done.stdout + done.stderr
    summary: dict[str, Any] = json.loads(done.stdout)
    return summary


@pytest.fixture(params=["sqlite", "postgresql"])
def databases(request: pytest.FixtureRequest) -> Iterator[Callable[[], list[str]]]:
    """Where a new lab keeps its index: ``[]`` (SQLite in its data folder), or
    ``["--database", URL]`` of a fresh PostgreSQL database, each call a new one."""
    if request.param == "sqlite":
        yield lambda: []
        return
    with postgres_databases() as fresh:
        yield lambda: ["--database", fresh()]


@pytest.fixture
def labs(cache: Path) -> Iterator[Callable[..., Served]]:
    """``labs(data, *args)``: `labd serve` processes, each stopped at the end."""
    made: list[Served] = []

    def make(data: Path, *args: str) -> Served:
        lab = Served(data, cache, "--no-robots", "--sandbox", "bwrap", *args)
        made.append(lab)
        return lab

    yield make
    for lab in made:
        lab.stop()


def listing(lab: Served) -> list[tuple[Any, ...]]:
    """The lab's trials as its API lists them: what a restore must give back."""
    rows = lab.get("/api/trials?limit=500")["trials"]
    return [
        (t["id"], t["status"], t["outcome"], t["data_digest"], (t["mcap"] or {}).get("digest"))
        for t in rows
    ]


def blob_files(folder: Path) -> dict[Path, tuple[int, int]]:
    """Each blob file of a backup, with its inode and modification time."""
    return {
        path: (path.stat().st_ino, path.stat().st_mtime_ns)
        for path in (folder / "blobs" / "sha256").rglob("*")
        if path.is_file()
    }


@pytest.mark.timeout(420 * SECOND)
def test_a_backup_of_a_running_lab_restores_a_lab_that_serves_the_same_records(
    databases, labs, tmp_path
):
    """Backed up while a trial runs: the backup restores into a fresh folder (and
    database) where the trials are those listed when it was taken, each record
    downloads byte for byte as the lab served it and verifies with the restored lab's
    keys, and the hosted repository is there; a second backup copies only new blobs; a
    restore into the restored lab is refused."""
    where = databases()
    lab = labs(tmp_path / "lab", "--workers", "1", "--allow-local-repos", *where)
    lab.token = lab.add_user("alice")
    lab.start()
    quick = lab.submit(GitRepo.create(tmp_path / "quick", controller(3)).path)
    lab.wait_ended([quick["id"]], 120)
    head = HostedRepos(lab.data / "git").commit(
        "alice", "robot", {"lab.toml": b"[controller]\n"}, "first", author="alice", when=WHEN
    )
    held = Held()
    slow = lab.submit(GitRepo.create(tmp_path / "slow", held.files).path, params=held.params)
    wait_for("the held trial to run", lambda: lab.stage(slow["id"]) == "running", 90 * SECOND)

    dest = tmp_path / "backup"
    made = ok("backup", str(dest), "--data", str(lab.data), *where)
    then = listing(lab)
    assert lab.trial(slow["id"])["status"] == "running", "the trial ended during the backup"
    assert [row[:2] for row in then] == [(slow["id"], "running"), (quick["id"], "finished")]
    assert made["trials"] == 2 and made["git"] == ["alice/robot"]
    assert "signing.pem" in made["keys"] and (dest / "backup.json").is_file()
    assert made["copied"]["blobs"] == made["blobs"] > 0

    target = databases()
    restored_data = tmp_path / "restored"
    restored = ok("restore", str(dest), "--data", str(restored_data), *target)
    assert restored["trials"] == 2

    # the trial ends; a second backup into the same folder copies only its blobs
    assert held.let_go() == 1
    [ended] = lab.wait_ended([slow["id"]], 120 * SECOND)
    assert ended["reason"].startswith("the controller exited with 0"), ended
    before = blob_files(dest)
    again = ok("backup", str(dest), "--data", str(lab.data), *where)
    after = blob_files(dest)
    assert {path: after[path] for path in before} == before, "a blob was copied again"
    assert again["copied"]["blobs"] == len(after) - len(before) > 0
    assert again["copied"]["present"] == len(before)

    # the restored lab serves the trials as they were when the backup was taken
    second = labs(restored_data, "--workers", "0", *target)
    second.start()
    assert listing(second) == then
    keys = tmp_path / "restored-keys.json"
    keys.write_text(httpx.get(f"{second.server}/api/keys", timeout=30).text)
    original = httpx.get(f"{lab.server}/api/trials/{quick['id']}/data.mcap", timeout=30)
    mcap = tmp_path / "quick.mcap"
    second.labd("download", str(quick["id"]), "-o", str(mcap))
    assert mcap.read_bytes() == original.content
    assert "sha256:" + hashlib.sha256(mcap.read_bytes()).hexdigest() == then[1][4]
    verified = second.labd("verify", str(mcap), "--key", str(keys))
    assert f"verified: trial {quick['id']}" in verified.stdout
    git = ["git", "--git-dir", str(restored_data / "git" / "alice" / "robot.git")]
    assert subprocess.run([*git, "rev-parse", "main"], capture_output=True, text=True,
                          check=True).stdout.strip() == head  # fmt: skip

    refused = labd("restore", str(dest), "--data", str(restored_data), *target)
    assert refused.returncode == 2, refused.stdout + refused.stderr
    assert f"a lab serves {restored_data} ({second.server})" in refused.stderr
    second.stop()  # stopped, the restored lab's index still refuses a second restore
    refused = labd("restore", str(dest), "--data", str(restored_data), *target)
    assert refused.returncode == 2, refused.stdout + refused.stderr
    assert "already holds 2 trial(s)" in refused.stderr
    assert len(refused.stderr.strip().splitlines()) == 1
