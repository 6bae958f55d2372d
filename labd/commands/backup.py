"""``labd backup`` and ``labd restore``: a whole lab copied while it runs, and brought up
elsewhere.

    labd backup DEST [--data DIR] [--database URL] [--blobs URL] [--blobs-option K=V] [--json]
    labd restore SRC --data DIR [--key FILE] [--database URL] [--blobs URL]
                 [--blobs-option K=V] [--json]

A backup folder holds the index (``index.sqlite``, whatever database the lab runs on),
the blobs its rows name (``blobs/``), the lab's keys (``keys/``: the signing key, every
public key it used, the secrets of reservations and held-out suites) and the
playground's hosted repositories (``git/``), and, written last, ``backup.json``. The
steps run in that order while the lab goes on (``repository.backup`` says why the
result is consistent): the index at one moment, then the blobs, which never change and
were stored before any row named them, then the keys, of which none is ever removed,
then each repository under its lock, whose commits only ever add. A second backup into
the same folder copies only the blobs it lacks.

The manifest is removed when a backup starts and written only once everything else is
on disk, signed with the lab's key, so a backup that failed (a full disk, an unreadable
blob: one line, exit 3) never looks finished, and ``labd restore`` refuses it. ``labd
restore`` also refuses a target that holds an archive already, a backup whose index
file changed, and one of a newer schema; an older one is upgraded as ``labd migrate``
would. It copies the blobs, keys and repositories first and the rows last, in one
transaction, so a restore that failed can be run again. Stop the target lab while it
runs.

Both often run as root, so neither trusts a folder or a link it did not make
(``repository.nofollow``): a backup writes only into a folder of its user's that it made,
or that is empty, or that holds an earlier backup of this lab (its manifest signed by the
lab's key), reached through no link another user could have made, holding none, and makes
it private (0700 folders, files for their owner alone). A restore refuses a backup that
holds any link, whose manifest its own signing key did not sign (or, with ``--key``, whose
signing key is not among the lab's public keys given), or whose index rows say other than
the lab's signature of each (``repository.signed_rows``).
"""

from __future__ import annotations

import argparse
import contextlib
import errno
import logging
import os
import shutil
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import asdict, replace
from pathlib import Path
from typing import Any

import sqlalchemy as sa

from labd import __version__, datalock
from labd.commands import settings
from labd.commands.common import ExitCode, emit, fail, json_option
from labd.hosted import HostedRepos
from labd.service import ServiceConfig
from repository import backup as store
from repository import backup_trust as trust
from repository import nofollow
from repository.blobs import BlobStore
from repository.errors import (
    ArchiveError,
    BackupDamaged,
    BackupError,
    BackupForged,
    TargetNotEmpty,
)
from repository.index import SCHEMA_VERSION, connect
from repository.signing import SIGNING, KeyFileError, Keyring, load_keys

KEYS = store.KEYS
GIT = store.GIT
PROGRESS_EVERY = 2.0  # seconds between progress lines on stderr
UNFINISHED = {  # what a failure leaves, as its message ends
    "backup": "the backup is not finished (no backup.json)",
    "restore": "nothing was restored into the index (run the restore again once fixed)",
}


class Failed(Exception):
    """A backup or restore stopped; ``code`` is the exit code (2 refused, 3 failed)."""

    def __init__(self, message: str, code: ExitCode) -> None:
        self.code = code
        super().__init__(message)


def _where(parser: argparse.ArgumentParser, data: settings.Setting) -> None:
    """``data`` (the lab's, or the new lab's), and the lab's database and blob store."""
    settings.add(parser, [data, *map(settings.get, ("database", "blobs", "blobs_option"))])
    json_option(parser)


def add_backup_parser(commands: Any) -> None:
    p = commands.add_parser(
        "backup",
        help="copy the lab (index, blobs, keys, hosted repositories) into a folder, online",
    )
    p.add_argument(
        "dest",
        type=Path,
        metavar="DEST",
        help="a new folder, or an earlier backup's (then only new blobs are copied)",
    )
    _where(p, settings.get("data"))


def add_restore_parser(commands: Any) -> None:
    p = commands.add_parser("restore", help="bring a backup up as a new lab")
    p.add_argument("src", type=Path, metavar="SRC", help="a folder labd backup made")
    p.add_argument(
        "--key",
        type=Path,
        metavar="FILE",
        help="the lab's public keys (what its /api/keys answers, or one PEM key): the"
        " backup's signing key must be one of them, and every signature is held to them",
    )
    data = settings.get("data")
    said = "the new lab's data folder, for its keys and repositories (no default)"
    _where(p, replace(data, help=said, default=None))


def add_parser(commands: Any) -> None:
    """Both commands: ``backup`` and ``restore``."""
    add_backup_parser(commands)
    add_restore_parser(commands)


def main(args: argparse.Namespace) -> int:
    run = backup if args.command == "backup" else restore
    try:
        data = run(args)
    except Failed as err:
        return fail(args, str(err), err.code)
    except BackupDamaged as err:
        return fail(args, str(err), ExitCode.ERROR)
    except BackupError as err:  # refused: a target not empty, a schema, no archive there
        return fail(args, str(err), ExitCode.USAGE)
    except ArchiveError as err:
        return fail(args, str(err), ExitCode.ERROR)
    except OSError as err:
        return fail(args, _os_error(err, UNFINISHED[args.command]), ExitCode.ERROR)
    except sa.exc.SQLAlchemyError as err:
        return fail(args, _database_error(err, UNFINISHED[args.command]), ExitCode.ERROR)
    emit(args, data, lambda: _said(args.command, data))
    return 0


# -- backup ----------------------------------------------------------------------------------


def backup(args: argparse.Namespace) -> dict[str, Any]:
    """Make or refresh the backup in ``args.dest``; its summary."""
    config = _config(args)
    if args.database is None and not (config.data / "index.sqlite").exists():
        raise Failed(
            f"no lab in {config.data} (no index.sqlite); give --data or --database",
            ExitCode.USAGE,
        )
    lab_keys = trust.KeyFiles.read(config.data / KEYS)
    if lab_keys.signing is None:
        raise Failed(
            f"no signing key in {config.data / KEYS}: a backup is signed with the lab's key"
            " (labd serve makes it); give the lab's --data",
            ExitCode.USAGE,
        )
    dest = _dest(args.dest, config.data, lab_keys)
    (dest / store.MANIFEST_FILE).unlink(missing_ok=True)  # unfinished from here on

    shot = store.snapshot(config.database_url, dest / store.INDEX_FILE)
    progress = Progress("backup")
    source = BlobStore(config.blobs_url, dict(config.blob_options) or None)
    copied, unreadable = _copy_blobs(
        dest / store.INDEX_FILE, source, BlobStore(str(dest / store.BLOBS)), progress
    )
    keys = _replace(dest / KEYS, lambda new: _copy_keys(config.data / KEYS, new))
    repos = _replace(dest / GIT, lambda new: HostedRepos(config.data / GIT).copy_all(new))
    if unreadable:
        raise Failed(
            f"{unreadable} in {source.url}; the backup is not finished (no backup.json):"
            " repair the store (a rerun's record heals its blob), then back up again",
            ExitCode.ERROR,
        )
    nofollow.make_private(dest)  # the blobs (0444 in a store), the repositories' files
    os.sync()  # every file of the backup on disk before the manifest says it is whole
    manifest = store.Manifest(
        labd=__version__,
        schema=shot.schema,
        made=shot.made,
        index_sha256=store.file_sha256(dest / store.INDEX_FILE),
        rows=shot.rows,
        blobs=copied.blobs,
        blob_bytes=copied.total_bytes,
        keys=keys,
        git=repos,
        key_sha256={n: store.file_sha256(dest / KEYS / n) for n in keys},
    )
    # signed with the signing key as the backup holds it (a rotation meanwhile: the new one)
    manifest = manifest.signed(Keyring(dest / KEYS))
    manifest.write(dest)
    return {
        "backup": str(dest),
        **asdict(manifest),
        "trials": manifest.trials,
        "copied": {"blobs": copied.copied, "bytes": copied.bytes, "present": copied.present},
    }


def _dest(given: Path, data: Path, lab_keys: trust.KeyFiles) -> Path:
    """DEST, reached through no link another user could have made (``UnsafeFolder``
    otherwise): made now (0700), or one of this user's that is empty or holds an earlier
    backup of this lab, holding no link; made private either way."""
    if given.absolute() == data.absolute() or (given.exists() and given.samefile(data)):
        raise Failed("DEST is the lab's own data folder; give another folder", ExitCode.USAGE)
    dest, made = nofollow.reach(given, create=True)
    if not made:
        trust.check_earlier(dest, lab_keys.public)
    nofollow.make_private(dest)
    return dest


def _copy_keys(source: Path, dest: Path) -> list[str]:
    """The key folder's files, the signing key first: a rotation meanwhile adds a public
    key, copied after it, and never removes one."""
    if not source.is_dir():
        return []
    names = sorted(p.name for p in source.iterdir() if p.is_file() and not p.name.startswith("."))
    names.sort(key=lambda name: name != SIGNING)
    for name in names:
        shutil.copy2(source / name, dest / name)
    return names


def _replace(folder: Path, fill: Callable[[Path], list[str]]) -> list[str]:
    """Fill a new folder (0700) beside ``folder``, then put it in ``folder``'s place."""
    new = folder.with_name(f".{folder.name}.new")
    old = folder.with_name(f".{folder.name}.old")
    for leftover in (new, old):
        shutil.rmtree(leftover, ignore_errors=True)
    new.mkdir(mode=nofollow.FOLDER)
    made = fill(new)
    if folder.exists():
        folder.rename(old)
    new.rename(folder)
    shutil.rmtree(old, ignore_errors=True)
    return made


# -- restore ---------------------------------------------------------------------------------


def restore(args: argparse.Namespace) -> dict[str, Any]:
    """Bring the backup in ``args.src`` up in the lab ``args.data`` names; a summary."""
    if args.data is None:
        raise Failed("give --data DIR: the new lab's data folder", ExitCode.USAGE)
    config = _config(args)
    running = datalock.holder(config.data)
    if running is not None:
        where = running.get("http", f"pid {running.get('pid', '?')}")
        raise Failed(f"a lab serves {config.data} ({where}): stop it, then restore", ExitCode.USAGE)
    src = Path(os.path.realpath(args.src))  # SRC as the operator named it; no link inside
    if config.data.resolve() == src:
        raise Failed("--data is the backup's own folder; give the new lab's", ExitCode.USAGE)
    opened = trust.open_backup(src, _given_keys(args.key))
    manifest = opened.manifest
    config.data.mkdir(mode=0o700, parents=True, exist_ok=True)
    # every row held to the lab's signatures (in a private copy) before the target is
    # opened: a forged backup leaves the new lab as it was
    with trust.checked_index(opened, config.data) as index, _engine(config) as engine:
        store.check_empty(engine)
        hosted = HostedRepos(config.data / GIT)
        if held := [f"{u}/{n}" for u in hosted.users() for n in hosted.names(u)]:
            listed = ", ".join(held)
            raise TargetNotEmpty(str(config.data / GIT), f"hosted repositories ({listed})")
        progress = Progress("restore")
        target = BlobStore(config.blobs_url, dict(config.blob_options) or None)
        backed_up = BlobStore(str(src / store.BLOBS))
        copied, unreadable = _copy_blobs(index, backed_up, target, progress)
        if unreadable:
            raise Failed(
                f"{unreadable} in the backup {src}; nothing was restored into the index",
                ExitCode.ERROR,
            )
        keys = _restore_keys(opened.keys, config.data / KEYS)
        # the repositories wait beside DATA/git until the rows are in, so a restore
        # that failed leaves DATA/git empty and can be run again
        staged = config.data / f".{GIT}.restore"
        shutil.rmtree(staged, ignore_errors=True)
        repos = _copy_git(HostedRepos(src / GIT), staged)
        if found := nofollow.links(staged) if staged.exists() else []:
            raise BackupForged(str(src), f"a link appeared in git/ ({found[0]})")
        rows = store.restore_index(index, engine)
        _move_git(staged, config.data / GIT, repos)
    return {
        "restored": str(src),
        "data": str(config.data),
        "database": store._shown(config.database_url),
        "blobs_url": config.blobs_url,
        "made": manifest.made,
        "schema": {"backup": manifest.schema, "now": SCHEMA_VERSION},
        "rows": rows,
        "trials": rows.get("trials", 0),
        "copied": {"blobs": copied.copied, "bytes": copied.bytes, "present": copied.present},
        "keys": keys,
        "git": repos,
        "signed_by": opened.keys.signing,
    }


@contextlib.contextmanager
def _engine(config: ServiceConfig) -> Iterator[sa.Engine]:
    """The target's index, disposed of at the end."""
    engine = connect(config.database_url)
    try:
        yield engine
    finally:
        engine.dispose()


def _given_keys(path: Path | None) -> dict[str, Any] | None:
    """The lab's public keys from ``--key`` (as ``labd verify`` reads them), or None."""
    if path is None:
        return None
    try:
        return dict(load_keys(path.read_bytes(), str(path)))
    except (OSError, KeyFileError) as err:
        raise Failed(f"--key: {err}", ExitCode.USAGE) from None


def _restore_keys(keys: trust.KeyFiles, dest: Path) -> list[str]:
    """The backup's keys (as read and checked) into the lab's key folder, each file whole
    (0600, renamed into place); a file of the same name is replaced, other public keys
    stay."""
    dest.mkdir(mode=0o700, parents=True, exist_ok=True)
    for name, data in sorted(keys.files.items()):
        tmp = dest / f".{name}.restore"
        tmp.unlink(missing_ok=True)
        flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC
        with os.fdopen(os.open(tmp, flags, nofollow.FILE), "wb") as out:
            out.write(data)
        tmp.replace(dest / name)
    return sorted(keys.files)


def _copy_git(backup: HostedRepos, root: Path) -> list[str]:
    """The backup's hosted repositories into ``root`` (names held to the lab's rule);
    ``USER/NAME`` of each."""
    copied = []
    for user in backup.users():
        for name in backup.names(user):
            target = root / user / f"{name}.git"
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copytree(backup.path(user, name), target, symlinks=True)
            copied.append(f"{user}/{name}")
    return copied


def _move_git(staged: Path, root: Path, repos: list[str]) -> None:
    """Move the staged repositories into the lab's ``root`` (renames, on one disk)."""
    for repo in repos:
        user, name = repo.split("/")
        (root / user).mkdir(parents=True, exist_ok=True)
        (staged / user / f"{name}.git").rename(root / user / f"{name}.git")
    shutil.rmtree(staged, ignore_errors=True)


# -- shared ----------------------------------------------------------------------------------


def _config(args: argparse.Namespace) -> ServiceConfig:
    return ServiceConfig(
        data=args.data,
        database=args.database,
        blobs=args.blobs,
        blob_options=dict(args.blobs_option),
    )


def _copy_blobs(
    index: Path, source: BlobStore, dest: BlobStore, progress: Progress
) -> tuple[store.BlobCopy, str]:
    """Copy the blobs the index names; what was done, and the unreadable ones in words
    ("" if none)."""
    with store.index_connection(index) as db, _store_quiet():
        total = store.count_named(db)
        copied = store.copy_blobs(store.named_blobs(db), total, source, dest, progress)
        shown = [
            f"{digest} ({store.owner(db, digest)}: {why})"
            for digest, why in list(copied.unreadable.items())[:3]
        ]
    progress.end(copied.blobs, total, copied.bytes)
    if not shown:
        return copied, ""
    more = len(copied.unreadable) - len(shown)
    listed = "; ".join(shown) + (f"; and {more} more" if more > 0 else "")
    return copied, f"{len(copied.unreadable)} blob(s) could not be read: {listed}"


@contextlib.contextmanager
def _store_quiet() -> Iterator[None]:
    """The blob store's own error for each damaged blob unsaid (unless --log-level asks
    for detail): the command's last line names the blobs it could not read, once."""
    logger = logging.getLogger("repository.blobs")
    if logging.getLogger().getEffectiveLevel() < logging.WARNING:
        yield
        return
    level = logger.level
    logger.setLevel(logging.CRITICAL)
    try:
        yield
    finally:
        logger.setLevel(level)


class Progress:
    """Progress of a long copy on stderr, a line every ``PROGRESS_EVERY`` seconds."""

    def __init__(self, command: str) -> None:
        self.command = command
        self.started = time.monotonic()
        self.last = self.started
        self.shown = False

    def __call__(self, done: int, total: int, copied: int) -> None:
        now = time.monotonic()
        if now - self.last >= PROGRESS_EVERY:
            self.last = now
            self.shown = True
            self._line(done, total, copied, "")

    def end(self, done: int, total: int, copied: int) -> None:
        """The last line, if any was shown: a short copy says nothing."""
        if self.shown:
            self._line(done, total, copied, f" in {time.monotonic() - self.started:.0f} s")

    def _line(self, done: int, total: int, copied: int, more: str) -> None:
        line = f"labd {self.command}: blobs {done}/{total}, {_size(copied)} copied{more}"
        print(line, file=sys.stderr, flush=True)


def _size(n: int) -> str:
    """A number of bytes, as a person reads it."""
    if n < 1024:
        return f"{n:,} bytes"
    size = float(n)
    for unit in ("KiB", "MiB", "GiB"):
        size /= 1024
        if size < 1024 or unit == "GiB":
            break
    return f"{size:.1f} {unit}"


def _os_error(err: OSError, unfinished: str) -> str:
    where = f"{err.filename}: " if err.filename else ""
    if err.errno == errno.ENOSPC:
        return f"{where}no space left on the device; {unfinished}"
    return f"{where}{err.strerror or err}; {unfinished}"


def _database_error(err: sa.exc.SQLAlchemyError, unfinished: str) -> str:
    cause = getattr(err, "orig", None) or err
    first = str(cause).strip().splitlines()[0] if str(cause).strip() else type(cause).__name__
    if "disk is full" in first:
        return f"no space left on the device ({first}); {unfinished}"
    return f"the database: {first}; {unfinished}"


def _said(command: str, data: dict[str, Any]) -> list[str]:
    copied = data["copied"]
    blobs = (
        f"{copied['blobs']} blob(s) copied ({_size(copied['bytes'])}),"
        f" {copied['present']} already there"
    )
    if command == "backup":
        return [
            f"backed up {data['trials']} trial(s) (the index as of {data['made']}) into"
            f" {data['backup']}",
            f"  blobs: {blobs}",
            f"  keys: {len(data['keys'])} file(s); hosted repositories: {len(data['git'])}",
            f"  index {data['index_sha256']}; the backup holds the lab's signing key: keep it"
            " private",
        ]
    schema = data["schema"]
    upgraded = (
        f" (upgraded from schema {schema['backup']})" if schema["backup"] != schema["now"] else ""
    )
    return [
        f"restored {data['trials']} trial(s) from {data['restored']} (as of {data['made']})"
        f" into {data['database']}{upgraded}",
        f"  blobs: {blobs} into {data['blobs_url']}",
        f"  keys: {len(data['keys'])} file(s); hosted repositories: {len(data['git'])}",
        f"  every signature checked; the backup was signed by {data['signed_by']}: the lab's"
        " key, if its /api/keys lists it (--key FILE checks that too)",
        f"  start it: labd serve --data {data['data']}"
        + (f" --database {data['database']}" if not data["database"].startswith("sqlite") else ""),
    ]
