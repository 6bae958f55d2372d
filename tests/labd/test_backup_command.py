"""`labd backup` and `labd restore` on a lab's folder: keys and hosted repositories come
back as they were; a failure is one line and an exit code, never a backup that looks
finished; a restore refuses what it must."""

from __future__ import annotations

import json
import os
import stat
import subprocess
from pathlib import Path

import pytest

from labd import cli
from labd.hosted import HostedRepos
from repository import backup
from repository.blobs import BlobStore
from repository.index import Index
from repository.reservations import load_secret
from repository.signing import SIGNING, Keyring
from tests.faults.conftest import s3, small_disk  # noqa: F401 (fixtures)
from tests.faults.slow import S3Server
from tests.repository.test_backup import fill

WHEN = 1_700_000_000


def labd(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    """Run ``labd backup|restore ...`` in this process: its exit code, stdout, stderr."""
    code = cli.main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


@pytest.fixture
def data_and_blobs(tmp_path: Path) -> tuple[Path, dict[str, str]]:
    """A lab's data folder: its index and blobs (``fill``, its filed trial signed with
    the lab's key), keys, a hosted repository."""
    data = tmp_path / "lab"
    data.mkdir()
    index = Index.open(backup.sqlite_url(data / "index.sqlite"))
    blobs = fill(index, BlobStore(str(data / "blobs")), Keyring(data / "keys"))
    index.close()
    load_secret(data / "keys" / "reservations.secret")
    blobs["head"] = HostedRepos(data / "git").commit(
        "alice", "robot", {"lab.toml": b"[controller]\n"}, "first", author="alice", when=WHEN
    )
    return data, blobs


def test_keys_and_repositories_come_back_as_they_were(data_and_blobs, tmp_path, capsys):
    """The signing key stays the lab's alone (0600, in a 0700 folder) in the backup and
    the restored lab; the secrets and the public key are the same bytes; the hosted
    repository has the same head; the backup checks against the lab's public keys as
    its /api/keys gives them (``--key``)."""
    data, blobs = data_and_blobs
    dest, restored = tmp_path / "backup", tmp_path / "restored"
    code, out, err = labd(capsys, "backup", str(dest), "--data", str(data))
    assert code == 0, err
    assert out.startswith("backed up 2 trial(s) (the index as of ")
    assert "the backup holds the lab's signing key: keep it private" in out
    lab_keys = tmp_path / "lab-keys.json"
    lab_keys.write_text(json.dumps({"keys": Keyring(data / "keys").public_keys()}))
    code, out, err = labd(capsys, "restore", str(dest), "--data", str(restored), "--json",
                          "--key", str(lab_keys))  # fmt: skip
    assert code == 0, err
    summary = json.loads(out)
    assert summary["trials"] == 2 and summary["git"] == ["alice/robot"]
    assert summary["signed_by"] == Keyring(data / "keys").current
    for keys in (dest / "keys", restored / "keys"):
        assert stat.S_IMODE(keys.stat().st_mode) == 0o700
        assert stat.S_IMODE((keys / SIGNING).stat().st_mode) == 0o600
        for name in os.listdir(data / "keys"):
            assert (keys / name).read_bytes() == (data / "keys" / name).read_bytes(), name
    assert Keyring(restored / "keys").current == Keyring(data / "keys").current
    head = subprocess.run(
        ["git", "--git-dir", str(restored / "git" / "alice" / "robot.git"), "rev-parse", "main"],
        capture_output=True,
        text=True,
        check=True,
    )
    assert head.stdout.strip() == blobs["head"]
    assert BlobStore(str(restored / "blobs")).read_bytes(blobs["mcap"]) == b"a record" * 1000


def test_an_unreadable_blob_fails_in_one_line_and_the_backup_is_not_finished(
    data_and_blobs, tmp_path, capsys
):
    """A record damaged in the lab's store: the backup exits 3 with one line naming the
    blob and its trial, and the folder of an earlier, finished backup has no manifest
    any more (a restore refuses it)."""
    data, blobs = data_and_blobs
    dest = tmp_path / "backup"
    assert labd(capsys, "backup", str(dest), "--data", str(data))[0] == 0
    damaged = Path(BlobStore(str(data / "blobs")).path(blobs["mcap"]))
    damaged.chmod(0o644)
    damaged.write_bytes(b"A record" + b"a record" * 999)
    (Path(BlobStore(str(dest / "blobs")).path(blobs["mcap"]))).unlink()
    code, out, err = labd(capsys, "backup", str(dest), "--data", str(data))
    assert code == 3 and out == ""
    assert len(err.strip().splitlines()) == 1, err
    assert f"1 blob(s) could not be read: {blobs['mcap']} (trial 1's record: damaged" in err
    assert "the backup is not finished (no backup.json)" in err
    assert not (dest / backup.MANIFEST_FILE).exists()
    code, _, err = labd(capsys, "restore", str(dest), "--data", str(tmp_path / "r"))
    assert code == 3 and "no backup.json (a backup that did not finish" in err


@pytest.mark.integration
def test_a_full_disk_fails_in_one_line_and_the_backup_is_not_finished(
    data_and_blobs,
    tmp_path,
    capsys,
    small_disk,  # noqa: F811 (the fixture)
):
    """A backup folder on a disk too small for a record: exit 3, one line saying the
    disk is full, and no manifest."""
    data, _blobs = data_and_blobs
    big = BlobStore(str(data / "blobs")).put_bytes(os.urandom(2 << 20))
    index = Index.open(backup.sqlite_url(data / "index.sqlite"))
    index.update(1, stdout=big)
    index.close()
    dest = small_disk(tmp_path / "small", 1 << 20)
    code, out, err = labd(capsys, "backup", str(dest / "b"), "--data", str(data))
    assert code == 3 and out == ""
    assert len(err.strip().splitlines()) == 1, err
    assert "no space left on the device" in err
    assert not (dest / "b" / backup.MANIFEST_FILE).exists()


def test_a_restore_refuses_a_changed_backup_and_a_lab_that_holds_trials(
    data_and_blobs, tmp_path, capsys
):
    """A backup whose index changed since (exit 3), into a lab that holds trials (exit
    2), without --data (exit 2): one line each, and the target is left as it was."""
    data, _ = data_and_blobs
    dest = tmp_path / "backup"
    assert labd(capsys, "backup", str(dest), "--data", str(data))[0] == 0
    code, _, err = labd(capsys, "restore", str(dest))
    assert (code, err) == (2, "labd restore: give --data DIR: the new lab's data folder\n")
    code, _, err = labd(capsys, "restore", str(dest), "--data", str(data))
    assert code == 2 and "lab/index.sqlite already holds 2 trial(s); restore only" in err
    index = dest / backup.INDEX_FILE
    index.write_bytes(index.read_bytes() + b"\0")
    code, _, err = labd(capsys, "restore", str(dest), "--data", str(tmp_path / "r"))
    assert code == 3 and "index.sqlite hashes to sha256:" in err
    assert len(err.strip().splitlines()) == 1
    assert not (tmp_path / "r").exists()


def test_a_backup_never_writes_into_a_folder_of_other_files(data_and_blobs, tmp_path, capsys):
    """DEST that holds other files, or is the lab's own folder, is refused (exit 2)."""
    data, _ = data_and_blobs
    other = tmp_path / "documents"
    other.mkdir()
    (other / "notes.txt").write_text("mine")
    code, _, err = labd(capsys, "backup", str(other), "--data", str(data))
    assert code == 2 and "holds other files" in err
    assert sorted(p.name for p in other.iterdir()) == ["notes.txt"]
    code, _, err = labd(capsys, "backup", str(data), "--data", str(data))
    assert code == 2 and "the lab's own data folder" in err


def test_a_restore_that_failed_can_be_run_again(data_and_blobs, tmp_path, capsys):
    """A record damaged in the backup: the restore exits 3 naming it, the new lab's
    index stays empty and its DATA/git holds nothing; once the blob is whole again the
    same restore succeeds into the same folder."""
    data, blobs = data_and_blobs
    dest, restored = tmp_path / "backup", tmp_path / "restored"
    assert labd(capsys, "backup", str(dest), "--data", str(data))[0] == 0
    record = Path(BlobStore(str(dest / "blobs")).path(blobs["mcap"]))
    whole = record.read_bytes()
    record.chmod(0o644)
    record.write_bytes(b"A" + whole[1:])
    code, _, err = labd(capsys, "restore", str(dest), "--data", str(restored))
    assert code == 3, err
    assert f"{blobs['mcap']} (trial 1's record: damaged" in err
    assert "nothing was restored into the index" in err
    assert not (restored / "git").exists()
    record.write_bytes(whole)
    code, out, err = labd(capsys, "restore", str(dest), "--data", str(restored), "--json")
    assert code == 0, err
    assert json.loads(out)["copied"] == {"blobs": 1, "bytes": len(whole), "present": 3}
    assert sorted(p.name for p in restored.iterdir()) == ["blobs", "git", "index.sqlite", "keys"]


@pytest.mark.integration
def test_blobs_in_a_bucket_are_backed_up_and_restored_into_a_bucket(
    tmp_path,
    capsys,
    s3: S3Server,  # noqa: F811 (the fixture)
):
    """A lab whose blobs are in an S3 bucket: the backup copies them from it, and the
    restore puts them under another prefix, where a second restore finds them all."""
    data = tmp_path / "lab"
    data.mkdir()
    option = f"endpoint_url={s3.url}"
    index = Index.open(backup.sqlite_url(data / "index.sqlite"))
    bucket = BlobStore("s3://lab-archive/records", {"endpoint_url": s3.url})
    blobs = fill(index, bucket, Keyring(data / "keys"))
    index.close()
    dest = tmp_path / "backup"
    code, out, err = labd(capsys, "backup", str(dest), "--data", str(data),
                          "--blobs", "s3://lab-archive/records", "--blobs-option", option,
                          "--json")  # fmt: skip
    assert code == 0, err
    assert json.loads(out)["copied"]["blobs"] == 4
    restore = ["--blobs", "s3://lab-archive/restored", "--blobs-option", option, "--json"]
    code, out, err = labd(capsys, "restore", str(dest), "--data", str(tmp_path / "r"), *restore)
    assert code == 0, err
    assert json.loads(out)["copied"]["blobs"] == 4
    s3.fs.invalidate_cache()
    restored = BlobStore("s3://lab-archive/restored", {"endpoint_url": s3.url})
    assert restored.read_bytes(blobs["mcap"]) == b"a record" * 1000
    code, out, err = labd(capsys, "restore", str(dest), "--data", str(tmp_path / "r2"), *restore)
    assert code == 0, err
    assert json.loads(out)["copied"] == {"blobs": 0, "bytes": 0, "present": 4}
