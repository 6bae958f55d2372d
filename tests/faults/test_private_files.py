"""The lab's own files are its user's alone (issue 32, "Private files").

The data folder, the index (password and token hashes, held-out suites' seeds), the keys
(the signing key, the secrets reservations' keys and held-out seeds derive from) were
made readable by every local user (``DATA/`` 0755, ``index.sqlite`` 0644). Now the lab
makes them 0700 and 0600 wherever it creates them, ``labd serve`` says, one line per
path, which ones it finds wider and the chmod that makes them private; and a trial's
sandbox, whose uid is not the lab's, still runs from a private data folder.
"""

from __future__ import annotations

import json
import re
import stat
import subprocess
import sys
from pathlib import Path

import pytest

from labd.datalock import DataLock
from repository import backup
from repository.index import Index
from repository.reservations import load_secret
from repository.signing import SIGNING, Keyring
from tests.faults.conftest import Served
from tests.faults.slow import controller
from tests.helpers.githttp import GitRepo
from tests.helpers.sandboxes import BACKENDS


def mode(path: Path) -> int:
    return stat.S_IMODE(path.lstat().st_mode)


def labd(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "labd", *args],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )


def private(data: Path) -> dict[str, int]:
    """The modes of the lab's private paths, by path relative to ``data``."""
    paths = [data, data / "index.sqlite", data / "keys", data / "labd.lock"]
    paths += [*sorted((data / "keys").glob("*.secret")), data / "keys" / SIGNING]
    paths += [p for p in (data / "index.sqlite-wal", data / "index.sqlite-shm") if p.exists()]
    return {str(p.relative_to(data.parent)): mode(p) for p in paths if p.exists()}


def test_the_index_keys_and_lock_are_made_private(tmp_path):
    """An index made by ``Index.open`` (and its WAL), the keys' folder and secrets, the
    data folder and its lock: 0700 folders and 0600 files, whatever the umask says."""
    data = tmp_path / "lab"
    lock = DataLock.take(data)
    index = Index.open(backup.sqlite_url(data / "index.sqlite"))
    index.add_user("alice")
    Keyring(data / "keys")
    load_secret(data / "keys" / "reservations.secret")
    load_secret(tmp_path / "elsewhere" / "suites.secret")
    found = private(data)
    index.close()
    lock.release()
    assert "lab/index.sqlite-wal" in found, "the index in WAL mode has no WAL file"
    assert found == {path: 0o700 if path in ("lab", "lab/keys") else 0o600 for path in found}, {
        p: oct(m) for p, m in found.items()
    }
    assert mode(tmp_path / "elsewhere") == 0o700


def test_labd_users_makes_a_private_data_folder(tmp_path):
    """``labd users add`` on a folder that does not exist yet (an operator's first
    command): the folder is 0700 and its index 0600."""
    data = tmp_path / "new-lab"
    done = labd("users", "add", "alice", "--data", str(data), "--json")
    assert done.returncode == 0, done.stderr
    assert (mode(data), mode(data / "index.sqlite")) == (0o700, 0o600)


@pytest.mark.integration
def test_labd_serve_names_each_path_others_may_read(cache, tmp_path):
    """A lab whose folder, index, keys and secrets were left readable by others (as an
    older labd made them): ``labd serve`` says so, one line per path with its mode and
    the chmod to run, and serves on; a lab made now says nothing of the kind."""
    data = tmp_path / "lab"
    lab = Served(data, cache, "--no-robots", "--workers", "0").start()
    lab.stop()
    assert not re.search(r"chmod \d+ ", lab.log), lab.log
    found = private(data)
    assert found == {path: 0o700 if path in ("lab", "lab/keys") else 0o600 for path in found}, {
        p: oct(m) for p, m in found.items()
    }

    wide = {
        data: 0o755,
        data / "index.sqlite": 0o644,
        data / "keys": 0o755,
        data / "keys" / SIGNING: 0o644,
        data / "keys" / "suites.secret": 0o640,
    }
    for path, bits in wide.items():
        path.chmod(bits)
    lab = Served(data, cache, "--no-robots", "--workers", "0").start()
    lab.stop()
    lines = [line for line in lab.log.splitlines() if re.search(r"chmod \d+ ", line)]
    assert len(lines) == len(wide), lab.log
    for path, bits in wide.items():
        fix = "700" if path.is_dir() else "600"
        said = [line for line in lines if line.endswith(f"chmod {fix} {path}")]
        assert len(said) == 1, (path, lines)
        assert f"{bits:04o}" in said[0], said[0]


@pytest.mark.integration
@pytest.mark.timeout(300)
@pytest.mark.parametrize("sandbox", BACKENDS)
def test_a_trial_runs_from_a_private_data_folder(cache, tmp_path, sandbox):
    """With the data folder 0700 (root's, here), a trial's sandbox (bubblewrap or Docker,
    as a uid of its own) still reads its code and reaches the bridge below it: the trial
    runs to its end (not an error), and the folder stayed private."""
    data = tmp_path / "lab"
    lab = Served(data, cache, "--no-robots", "--workers", "1", "--sandbox", sandbox,
                 "--allow-local-repos")  # fmt: skip
    lab.token = lab.add_user("alice")
    try:
        lab.start()
        assert mode(data) == 0o700
        trial = lab.submit(GitRepo.create(tmp_path / "quick", controller(3)).path)
        [ended] = lab.wait_ended([trial["id"]], 180)
    finally:
        lab.stop()
    assert ended["status"] == "finished" and ended["outcome"] != "error", json.dumps(ended)
    assert mode(data) == 0o700 and mode(data / "index.sqlite") == 0o600
