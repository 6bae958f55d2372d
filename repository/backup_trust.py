"""What a backup and a restore trust: a folder to write into, a backup to read.

A backup holds the lab's signing key and secrets, and a restore puts what it holds into a
lab, so neither trusts a folder it did not make, nor a link in one (``repository.nofollow``
says how they are reached):

- ``check_earlier``: a backup writes only into a folder of its user's that no one else may
  write to and that is empty or holds an earlier backup of this lab (its manifest signed
  by one of this lab's keys), holding no link;
- ``open_backup``: a restore refuses a backup holding any link, a manifest the backup's
  own signing key (or, pinned, one of the keys given) did not sign, a key file or an
  index whose sha256 is not the one signed;
- ``checked_index``: then it holds a private copy of the index to the lab's signature of
  each row (``repository.signed_rows``) before anything of the backup enters the lab.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import stat
import tempfile
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path

import sqlalchemy as sa
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey, Ed25519PublicKey
from sqlalchemy.pool import NullPool

from repository import nofollow, signed_rows
from repository.backup import INDEX_FILE, KEYS, Manifest, sqlite_url
from repository.errors import BackupDamaged, BackupError, BackupForged, UnsafeFolder
from repository.index import SCHEMA_VERSION
from repository.migrate import upgrade
from repository.signing import SIGNING, key_id


@dataclass(frozen=True)
class KeyFiles:
    """A keys folder (a lab's, or a backup's): each file's bytes, the id of its signing
    key and every public key by id, read without following a link."""

    files: dict[str, bytes]
    signing: str | None
    public: dict[str, Ed25519PublicKey]

    @classmethod
    def read(cls, folder: Path) -> KeyFiles:
        """The keys in ``folder`` (none if there is no such folder); BackupError if a
        file of it is not what its name says."""
        files: dict[str, bytes] = {}
        if folder.is_dir() and not folder.is_symlink():
            for path in sorted(folder.iterdir()):
                if path.name.startswith(".") or not stat.S_ISREG(path.lstat().st_mode):
                    continue
                files[path.name] = nofollow.read_bytes(path)
        signing = None
        public: dict[str, Ed25519PublicKey] = {}
        try:
            if SIGNING in files:
                private = serialization.load_pem_private_key(files[SIGNING], password=None)
                if not isinstance(private, Ed25519PrivateKey):
                    raise ValueError(f"{SIGNING} is not an Ed25519 private key")
                signing = key_id(private.public_key())
            for name, data in files.items():
                if name.startswith("ed25519-") and name.endswith(".pub.pem"):
                    key = serialization.load_pem_public_key(data)
                    if not isinstance(key, Ed25519PublicKey):
                        raise ValueError(f"{name} is not an Ed25519 public key")
                    public[key_id(key)] = key
        except (ValueError, TypeError) as err:
            raise BackupError(f"{folder}: {err}") from None
        return cls(files, signing, public)


def check_earlier(folder: Path, keys: Mapping[str, Ed25519PublicKey]) -> None:
    """UnsafeFolder unless a backup may write into ``folder``, which exists: this user's,
    no one else may write to it, holding no link, and either empty or an earlier backup of
    the lab whose public keys are ``keys`` (its manifest signed by one of them)."""
    st = folder.lstat()
    if st.st_uid != os.geteuid():
        raise UnsafeFolder(
            str(folder),
            f"belongs to uid {st.st_uid}, not to this user (uid {os.geteuid()}): another user"
            " may have prepared it; give a new folder",
        )
    if st.st_mode & 0o022:
        raise UnsafeFolder(
            str(folder),
            f"is {stat.S_IMODE(st.st_mode):04o}: other users may write to it; give a new"
            f" folder (or chmod 700 {folder})",
        )
    if not any(folder.iterdir()):
        return
    if found := nofollow.links(folder):
        raise UnsafeFolder(
            str(found[0]),
            "is a link (a backup labd made holds none; someone planted it): give a new folder",
        )
    try:
        manifest = Manifest.read(folder)
        manifest.verify(folder, keys, None)
    except BackupError as err:
        why = err.reason if isinstance(err, BackupDamaged) else str(err)
        raise UnsafeFolder(
            str(folder),
            f"holds other files than an earlier backup of this lab ({why}); give a new or"
            " empty folder, or an earlier backup's",
        ) from None


@dataclass(frozen=True)
class Opened:
    """A backup checked as a whole: no link in it, its manifest signed by its own signing
    key (and that key among the ones given, if any), its index the one signed."""

    folder: Path
    manifest: Manifest
    keys: KeyFiles
    trusted: dict[str, Ed25519PublicKey]  # what its signatures are held to


def open_backup(folder: Path, given: Mapping[str, Ed25519PublicKey] | None = None) -> Opened:
    """Check the backup in ``folder`` before anything of it is used: BackupForged if it
    holds a link, if its manifest's signature does not hold or is not by the backup's
    signing key (which, with ``given``, must be one of them), or a key file is not the
    one it signed; BackupDamaged if it did not finish or its index changed; BackupError
    for a newer schema."""
    if not folder.is_dir():
        raise BackupError(f"{folder} is not a folder")
    if found := nofollow.links(folder):
        listed = ", ".join(str(p) for p in found[: signed_rows.SAID])
        more = len(found) - signed_rows.SAID
        raise BackupForged(
            str(folder),
            f"it holds links, which labd never puts in a backup: {listed}"
            + (f" and {more} more" if more > 0 else ""),
        )
    manifest = Manifest.read(folder)
    keys = KeyFiles.read(folder / KEYS)
    if keys.signing is None or keys.signing not in keys.public:
        raise BackupForged(
            str(folder), f"keys/ holds no {SIGNING} with its public key (the lab's signing key)"
        )
    if given is not None and keys.signing not in given:
        raise BackupForged(
            str(folder),
            f"its signing key {keys.signing} (keys/{SIGNING}) is not among the keys given"
            f" ({', '.join(sorted(given)) or 'none'}): not the lab's backup, or its keys"
            " were replaced",
        )
    trusted = dict(given) if given is not None else keys.public
    manifest.verify(folder, trusted, keys.signing)
    for name, data in sorted(keys.files.items()):
        expected = manifest.key_sha256.get(name)
        if expected != f"sha256:{hashlib.sha256(data).hexdigest()}":
            raise BackupForged(str(folder), f"keys/{name} is not the file the lab signed")
    if missing := sorted(set(manifest.key_sha256) - set(keys.files)):
        raise BackupDamaged(str(folder), f"keys/{missing[0]} is missing")
    manifest.check(folder)
    return Opened(folder, manifest, keys, trusted)


@contextlib.contextmanager
def checked_index(opened: Opened, scratch: Path) -> Iterator[Path]:
    """A private copy of the backup's index under ``scratch`` (removed afterwards), in
    this labd's schema, every row of it borne out by the lab's signatures: BackupForged
    naming the rows that are not, or if the file changed since ``open_backup``."""
    with tempfile.TemporaryDirectory(prefix=".restore-", dir=scratch) as folder:
        copy = Path(folder) / INDEX_FILE
        digest = nofollow.copy_file(opened.folder / INDEX_FILE, copy)
        if digest != opened.manifest.index_sha256:
            raise BackupForged(
                str(opened.folder), f"{INDEX_FILE} changed while it was being restored"
            )
        engine = sa.create_engine(sqlite_url(copy), poolclass=NullPool)
        try:
            if opened.manifest.schema != SCHEMA_VERSION:
                upgrade(engine)
            with engine.connect() as db:
                problems = signed_rows.check(db, opened.trusted)
        finally:
            engine.dispose()
        if problems:
            raise BackupForged(
                str(opened.folder),
                "its index says other than the lab's signatures: " + signed_rows.summary(problems),
            )
        yield copy
