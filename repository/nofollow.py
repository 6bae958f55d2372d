"""Folders reached, read and made private without following a link others could make.

``labd backup`` and ``labd restore`` often run as root, on folders an operator names. A
link planted by a local user on the way to such a folder, or inside it, would turn
root's writes and reads anywhere: a hard link of a controller's printed output into
``/etc/cron.d``, a key file or a repository from outside a backup copied into a lab and
served. So:

- ``reach(path)`` walks the path one component at a time (``lstat``, never ``stat``).
  Each component, a link or a folder, must be one no other user could have made or
  could replace: in a folder only root or this user may write to (its owner one of them,
  no group or other write bit), or in a sticky folder (as ``/tmp``) and owned by root or
  this user. A link is followed only then; so no one else can rename a folder on the way
  once it has been checked, and what ``reach`` answers stays what it checked. Missing
  folders are made 0700, only where no one else could take their place.
- ``links(folder)``: every link (or device, fifo, socket) below a folder, for a refusal
  that names them. Inside a folder only this user may write to, none can appear later.
- ``make_private(folder)``: folders 0700, files stripped of group and other bits.
- ``read_bytes`` and ``copy_file`` open their source with ``O_NOFOLLOW``.

A Linux or BSD idea throughout: ``O_NOFOLLOW``, sticky folders, ``lstat``.
"""

from __future__ import annotations

import hashlib
import os
import stat
from collections.abc import Iterator
from pathlib import Path

from repository.errors import UnsafeFolder
from repository.units import MiB

FOLDER = 0o700  # private modes
FILE = 0o600
MAX_LINKS = 40  # links followed on one path (the kernel's own limit)
_READ = os.O_RDONLY | os.O_NOFOLLOW | os.O_CLOEXEC


def trusted_owners() -> frozenset[int]:
    """The uids whose folders and links this process may trust: root's and its own."""
    return frozenset({0, os.geteuid()})


def only_ours(st: os.stat_result) -> bool:
    """Whether no one but root and this user may add, remove or rename entries of the
    folder ``st`` describes."""
    return st.st_uid in trusted_owners() and not st.st_mode & (stat.S_IWGRP | stat.S_IWOTH)


def _sticky(st: os.stat_result) -> bool:
    """A folder whose entries only their owners (and the folder's) may rename, as /tmp."""
    return bool(st.st_mode & stat.S_ISVTX)


def _swappable(parent: os.stat_result, child: os.stat_result) -> bool:
    """Whether someone else could have made or could replace ``child``, an entry of the
    folder ``parent``: they may write the folder, and if it is sticky the entry is
    theirs."""
    if only_ours(parent):
        return False
    return not (_sticky(parent) and child.st_uid in trusted_owners())


def reach(path: Path, *, create: bool = False) -> tuple[Path, bool]:
    """The folder ``path``, as a path nobody but root and this user can redirect, and
    whether this call made it (``create``: the missing folders are made, 0700).

    UnsafeFolder if a component is a link another user could have made, a folder
    another user could swap, or not a folder.
    """
    pending = list(Path(os.path.abspath(path)).parts[1:])
    current = Path("/")
    here = os.lstat(current)
    followed = 0
    made = False
    while pending:
        name = pending.pop(0)
        if name in ("", "."):
            continue
        if name == "..":
            current = current.parent
            here = os.lstat(current)
            continue
        child = current / name
        made = False
        try:
            st = os.lstat(child)
        except FileNotFoundError:
            if not create:
                raise UnsafeFolder(str(path), f"{child} does not exist") from None
            if not only_ours(here) and not _sticky(here):
                raise UnsafeFolder(
                    str(path),
                    f"{current} is a folder other users may write to: they could put a"
                    " link in the place of a folder made there; make it in a folder only"
                    " root or this user may write to",
                ) from None
            os.mkdir(child, FOLDER)  # never follows: EEXIST if anything appeared there
            made = True
            st = os.lstat(child)
        if stat.S_ISLNK(st.st_mode):
            if _swappable(here, st):
                raise UnsafeFolder(
                    str(path),
                    f"{child} is a link in {current}, a folder other users may write to"
                    " (anyone could have made it point anywhere); give the path it"
                    " points to, if it is yours",
                )
            followed += 1
            if followed > MAX_LINKS:
                raise UnsafeFolder(str(path), f"more than {MAX_LINKS} links on the way")
            target = Path(os.readlink(child))
            if target.is_absolute():
                current = Path("/")
                here = os.lstat(current)
            pending = [*target.parts[1 if target.is_absolute() else 0 :], *pending]
            continue
        if not stat.S_ISDIR(st.st_mode):
            raise UnsafeFolder(str(path), f"{child} is not a folder")
        if _swappable(here, st):
            raise UnsafeFolder(
                str(path),
                f"{current} lets other users rename {name} (the folder on the way could be"
                " swapped for a link); use a path only root or this user may change",
            )
        current, here = child, st
    return current, made


def links(folder: Path) -> list[Path]:
    """Every entry below ``folder`` that is neither a file nor a folder (a link, most
    likely), in the order of a walk; the walk follows none of them."""
    found = []
    for top, dirs, files in os.walk(folder, followlinks=False):
        for name in sorted(dirs + files):
            path = Path(top, name)
            mode = os.lstat(path).st_mode
            if not (stat.S_ISDIR(mode) or stat.S_ISREG(mode)):
                found.append(path)
    return found


def walk(folder: Path) -> Iterator[tuple[Path, os.stat_result]]:
    """``folder`` and everything below it, with their ``lstat``; links are not followed."""
    yield folder, os.lstat(folder)
    for top, dirs, files in os.walk(folder, followlinks=False):
        for name in dirs + files:
            path = Path(top, name)
            yield path, os.lstat(path)


def make_private(folder: Path) -> None:
    """Folders 0700 and files without group or other bits, ``folder`` and all below it
    (links are left alone: the callers refuse them first)."""
    for path, st in walk(folder):
        mode = stat.S_IMODE(st.st_mode)
        if stat.S_ISDIR(st.st_mode):
            if mode != FOLDER:
                os.chmod(path, FOLDER)
        elif stat.S_ISREG(st.st_mode) and mode & 0o077:
            os.chmod(path, mode & 0o700)


def read_bytes(path: Path) -> bytes:
    """The bytes of the file ``path``; OSError (ELOOP) if it is a link."""
    fd = os.open(path, _READ)
    with os.fdopen(fd, "rb") as stream:
        return stream.read()


def copy_file(source: Path, dest: Path) -> str:
    """Copy the file ``source`` (not through a link) to a new file ``dest`` (0600; not
    through a link either); the ``sha256:HEX`` of the bytes copied."""
    sha = hashlib.sha256()
    fd = os.open(source, _READ)
    with os.fdopen(fd, "rb") as src:
        out_fd = os.open(
            dest, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC, FILE
        )
        with os.fdopen(out_fd, "wb") as out:
            while chunk := src.read(MiB):
                sha.update(chunk)
                out.write(chunk)
            out.flush()
            os.fsync(out.fileno())
    return f"sha256:{sha.hexdigest()}"


def sha256(path: Path) -> str:
    """The ``sha256:HEX`` of the file ``path``, read not through a link."""
    sha = hashlib.sha256()
    fd = os.open(path, _READ)
    with os.fdopen(fd, "rb") as stream:
        while chunk := stream.read(MiB):
            sha.update(chunk)
    return f"sha256:{sha.hexdigest()}"
