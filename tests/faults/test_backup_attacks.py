"""`labd backup` and `labd restore` attacked (issue 32, "Backup and restore follow no link").

The backup runs as root here, as it often does on a lab's machine, so a link it followed
really writes where the link points: every target is a folder of ``tmp_path`` standing
for one such as ``/etc/cron.d``. The attacks are those found on the code before:

- a local user prepares DEST: an empty ``index.sqlite`` made any folder pass for an
  earlier backup, and a link planted under ``blobs/`` received a hard link of a
  controller's printed output (in ``/etc/cron.d``: a root cron job);
- DEST, or a folder on its way, is a link into such a folder;
- a backup holding links: restore copied a key file, or a hosted repository, from
  outside the backup into the new lab, and served it;
- a backup whose index was edited (an outcome made better) and whose manifest's hash
  was recomputed restored, and served the forged outcome;
- a manifest signed by another key than the lab's.
"""

# ruff: noqa: F811 (the lab's data folder, imported from test_backup_command, is the tests' argument)
from __future__ import annotations

import json
import os
import sqlite3
import stat
from pathlib import Path

import pytest

from labd.hosted import HostedRepos
from repository import backup
from repository.index import Index
from repository.signing import SIGNING, Keyring
from tests.labd.test_backup_command import WHEN, data_and_blobs, labd  # noqa: F401 (the fixture)
from tests.repository.test_backup import sign_filed

STRANGER = 64999  # a local user's uid, who is not the lab's


def forged_outcome(dest: Path) -> None:
    """Edit the backup's index as an attacker with write access would: trial 1's outcome
    made ``success`` (the lab filed and signed ``fail``), and the manifest's sha256 of the
    index made right again."""
    with sqlite3.connect(dest / backup.INDEX_FILE) as db:
        db.execute("UPDATE trials SET outcome = 'success' WHERE id = 1")
    db.close()
    manifest = json.loads((dest / backup.MANIFEST_FILE).read_text())
    manifest["index_sha256"] = backup.file_sha256(dest / backup.INDEX_FILE)
    (dest / backup.MANIFEST_FILE).write_text(json.dumps(manifest))


def failed_trial(data: Path) -> None:
    """Make the lab's filed trial one that failed, signed so (as the lab files one)."""
    index = Index.open(backup.sqlite_url(data / "index.sqlite"))
    index.update(1, outcome="fail", metrics={"success": False, "reward": 0.5})
    sign_filed(index, Keyring(data / "keys"))
    index.close()


def files_in(folder: Path) -> list[str]:
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*"))


# -- backup: where it writes -------------------------------------------------------------


@pytest.mark.parametrize("owner", ["a local user", "the lab's user"])
def test_an_empty_index_makes_no_folder_an_earlier_backup(data_and_blobs, tmp_path, capsys, owner):
    """A folder holding an empty ``index.sqlite`` and a link under ``blobs/`` into a
    folder of root's (standing for /etc/cron.d) is no earlier backup, whoever owns it:
    the backup refuses it (exit 2) and nothing is written there or through the link."""
    data, blobs = data_and_blobs
    cron = tmp_path / "cron.d"
    cron.mkdir()
    prepared = tmp_path / "prepared"
    (prepared / "blobs" / "sha256").mkdir(parents=True)
    (prepared / backup.INDEX_FILE).touch()
    hex_ = blobs["stdout"].split(":")[1]
    (prepared / "blobs" / "sha256" / hex_[:2]).symlink_to(cron)
    if owner == "a local user":
        for path in (prepared, *prepared.rglob("*")):
            os.chown(path, STRANGER, STRANGER, follow_symlinks=False)
    before = files_in(prepared)
    code, out, err = labd(capsys, "backup", str(prepared), "--data", str(data))
    assert files_in(cron) == [], "the backup wrote through the planted link"
    assert files_in(prepared) == before
    assert code == 2, err
    assert out == "" and len(err.strip().splitlines()) == 1, err


def test_a_link_planted_in_an_earlier_backup_is_refused(data_and_blobs, tmp_path, capsys):
    """An earlier, finished backup of this lab in which a link under ``blobs/`` now
    points outside: the next backup refuses the folder naming the link (exit 2), and
    writes nothing through it."""
    data, blobs = data_and_blobs
    dest, cron = tmp_path / "backup", tmp_path / "cron.d"
    cron.mkdir()
    assert labd(capsys, "backup", str(dest), "--data", str(data))[0] == 0
    hex_ = blobs["stdout"].split(":")[1]
    folder = dest / "blobs" / "sha256" / hex_[:2]
    for path in folder.iterdir():
        path.chmod(0o600)
        path.unlink()
    folder.rmdir()
    folder.symlink_to(cron)
    code, _, err = labd(capsys, "backup", str(dest), "--data", str(data))
    assert files_in(cron) == [], "the backup wrote through the planted link"
    assert code == 2, err
    assert str(folder) in err and "link" in err, err


def test_dest_reached_through_a_link_another_user_could_make_is_refused(
    data_and_blobs, tmp_path, capsys
):
    """DEST that is a link to root's folder, or lies under a link in a folder every user
    may write to (as /tmp is), is refused (exit 2), and the folder it points to stays
    empty."""
    data, _ = data_and_blobs
    cron = tmp_path / "cron.d"
    cron.mkdir()
    shared = tmp_path / "shared"
    shared.mkdir()
    shared.chmod(0o1777)
    (shared / "link").symlink_to(cron)
    os.chown(shared / "link", STRANGER, STRANGER, follow_symlinks=False)
    for dest in (shared / "link", shared / "link" / "backup"):
        code, out, err = labd(capsys, "backup", str(dest), "--data", str(data))
        assert files_in(cron) == [], f"the backup into {dest} wrote through the link"
        assert code == 2, err
        assert "link" in err and out == "", err


# -- restore: what it reads ----------------------------------------------------------------


def test_a_restore_refuses_a_key_linked_from_outside_the_backup(data_and_blobs, tmp_path, capsys):
    """A backup whose ``keys/signing.pem`` is a link to another key file: the restore
    refuses it, naming the link (exit 3), and the new lab gets no key and no rows."""
    data, _ = data_and_blobs
    dest, restored = tmp_path / "backup", tmp_path / "restored"
    assert labd(capsys, "backup", str(dest), "--data", str(data))[0] == 0
    outside = Keyring(tmp_path / "outside-keys")
    signing = dest / "keys" / SIGNING
    signing.unlink()
    signing.symlink_to(outside.folder / SIGNING)
    code, _, err = labd(capsys, "restore", str(dest), "--data", str(restored))
    assert not (restored / "keys" / SIGNING).exists(), "the outside key was restored"
    assert not (restored / "index.sqlite").exists()
    assert code == 3, err
    assert str(signing) in err and "link" in err, err


def test_a_restore_refuses_a_repository_linked_from_outside_the_backup(
    data_and_blobs, tmp_path, capsys
):
    """A backup whose ``git/`` holds a link to a user's folder of repositories outside
    it: the restore refuses it (exit 3), and the new lab serves no such repository."""
    data, _ = data_and_blobs
    dest, restored = tmp_path / "backup", tmp_path / "restored"
    assert labd(capsys, "backup", str(dest), "--data", str(data))[0] == 0
    outside = HostedRepos(tmp_path / "outside-git")
    outside.commit("mallory", "evil", {"lab.toml": b"x"}, "planted", author="mallory", when=WHEN)
    (dest / "git" / "mallory").symlink_to(tmp_path / "outside-git" / "mallory")
    code, _, err = labd(capsys, "restore", str(dest), "--data", str(restored))
    assert not (restored / "git" / "mallory").exists(), "the outside repository was restored"
    assert code == 3, err
    assert str(dest / "git" / "mallory") in err, err


def test_an_edited_outcome_is_never_restored(data_and_blobs, tmp_path, capsys):
    """A backup whose index says a failed trial succeeded, its manifest's sha256 made to
    match: refused (exit 3), as the manifest's signature no longer holds; and nothing is
    restored."""
    data, _ = data_and_blobs
    failed_trial(data)
    dest, restored = tmp_path / "backup", tmp_path / "restored"
    assert labd(capsys, "backup", str(dest), "--data", str(data))[0] == 0
    forged_outcome(dest)
    code, _, err = labd(capsys, "restore", str(dest), "--data", str(restored))
    assert not (restored / "index.sqlite").exists(), "the forged outcome was restored"
    assert code == 3, err
    assert "backup.json" in err and "signature" in err, err


def test_an_edited_row_is_refused_even_under_a_manifest_signed_anew(
    data_and_blobs, tmp_path, capsys
):
    """Each row is held to its own signature too: with the manifest signed again by the
    lab's key (as one who held it could), the edited outcome is refused, naming trial 1
    and what its signature says."""
    data, _ = data_and_blobs
    failed_trial(data)
    dest, restored = tmp_path / "backup", tmp_path / "restored"
    assert labd(capsys, "backup", str(dest), "--data", str(data))[0] == 0
    forged_outcome(dest)
    manifest = backup.Manifest.read(dest)
    manifest.signed(Keyring(data / "keys")).write(dest)
    code, _, err = labd(capsys, "restore", str(dest), "--data", str(restored))
    assert code == 3, err
    assert "trial 1" in err and "outcome" in err and "'fail'" in err, err
    assert not (restored / "index.sqlite").exists()


def test_a_manifest_signed_by_another_key_is_refused(data_and_blobs, tmp_path, capsys):
    """A backup whose manifest another key signed (its public key added to ``keys/``) is
    refused; one whose whole ``keys/`` was replaced, every row signed again by the new
    key, is refused when the lab's public keys are given (``--key``)."""
    data, _ = data_and_blobs
    dest, restored = tmp_path / "backup", tmp_path / "restored"
    assert labd(capsys, "backup", str(dest), "--data", str(data))[0] == 0
    mallory = Keyring(tmp_path / "mallory-keys")
    public = mallory.public_keys()[mallory.current]
    (dest / "keys" / f"ed25519-{mallory.current.split(':')[1]}.pub.pem").write_text(public)
    manifest = backup.Manifest.read(dest)
    manifest.signed(mallory).write(dest)
    code, _, err = labd(capsys, "restore", str(dest), "--data", str(restored))
    assert code == 3, err
    assert "not signed by the lab's key" in err, err

    # the whole of keys/ replaced, every signature made again by the new key
    for path in (dest / "keys").iterdir():
        path.chmod(0o600)
        path.unlink()
    for path in mallory.folder.iterdir():
        (dest / "keys" / path.name).write_bytes(path.read_bytes())
    index = Index.open(backup.sqlite_url(dest / backup.INDEX_FILE))
    sign_filed(index, mallory)
    index.close()
    manifest = backup.Manifest.read(dest)
    replace = {"index_sha256": backup.file_sha256(dest / backup.INDEX_FILE)}
    backup.Manifest(**{**manifest.fields(), **replace}).signed(mallory).write(dest)
    lab_keys = tmp_path / "lab-keys.json"
    lab_keys.write_text(json.dumps({"keys": Keyring(data / "keys").public_keys()}))
    code, _, err = labd(
        capsys, "restore", str(dest), "--data", str(restored), "--key", str(lab_keys)
    )
    assert code == 3, err
    assert mallory.current in err and "not among the keys given" in err, err
    assert not (restored / "index.sqlite").exists()


def test_a_backup_and_its_files_are_the_lab_users_alone(data_and_blobs, tmp_path, capsys):
    """Every folder of a backup is 0700 and no file of it is readable by the group or
    others, DEST itself included; a second backup keeps them so."""
    data, _ = data_and_blobs
    dest = tmp_path / "backup"
    for _ in range(2):
        code, _, err = labd(capsys, "backup", str(dest), "--data", str(data))
        assert code == 0, err
        for path in (dest, *dest.rglob("*")):
            mode = stat.S_IMODE(path.lstat().st_mode)
            if path.is_dir():
                assert mode == 0o700, f"{path}: {oct(mode)}"
            else:
                assert mode & 0o077 == 0, f"{path}: {oct(mode)}"
