"""One lab per data folder: ``labd serve`` holds ``DATA/labd.lock`` while it runs.

Two labs on one archive would each run workers that claim the other's queue, and each
would rewrite what the other keeps in the folder. The lock is ``flock`` on the file,
which the kernel lets go when the process ends however it ends (a ``kill -9`` too), so a
crashed lab never leaves a stale lock behind. The file names the lab that holds it (its
pid and addresses), for the one line that refuses a second lab.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
from pathlib import Path

from labd.errors import LabError

NAME = "labd.lock"


class FolderInUse(LabError):
    """Another lab serves this data folder; ``holder`` is what it wrote of itself."""

    def __init__(self, data: Path, holder: dict[str, object]) -> None:
        self.data = data
        self.holder = holder
        where = holder.get("http") or holder.get("bridge") or "an address not yet known"
        pid = holder.get("pid")
        who = f"the lab at {where}" + (f" (pid {pid})" if pid else "")
        super().__init__(f"--data {data} is in use by {who}: stop it first, or give another --data")


class DataLock:
    """The lock of one data folder, held from ``take`` until ``release`` (or the end of
    the process)."""

    def __init__(self, path: Path, fd: int) -> None:
        self.path = path
        self._fd: int | None = fd

    @classmethod
    def take(cls, data: Path) -> DataLock:
        """Hold ``data``'s lock, or raise ``FolderInUse`` naming the lab that holds it."""
        data.mkdir(mode=0o700, parents=True, exist_ok=True)  # the lab's user's alone
        path = data / NAME
        fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o600)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = _read(fd)
            os.close(fd)
            raise FolderInUse(data, holder) from None
        lock = cls(path, fd)
        lock.note()
        return lock

    def note(self, **addresses: str) -> None:
        """Write who holds the lock: this process, and the addresses it serves at."""
        if self._fd is None:
            return
        text = json.dumps({"pid": os.getpid(), **addresses}).encode()
        os.ftruncate(self._fd, 0)
        os.pwrite(self._fd, text + b"\n", 0)

    def release(self) -> None:
        if self._fd is None:
            return
        with contextlib.suppress(OSError):
            os.ftruncate(self._fd, 0)
        os.close(self._fd)  # closing the descriptor lets the lock go
        self._fd = None


def holder(data: Path) -> dict[str, object] | None:
    """Who serves ``data`` now (what it wrote of itself), or None when no lab does."""
    try:
        fd = os.open(data / NAME, os.O_RDONLY | os.O_CLOEXEC)
    except FileNotFoundError:
        return None
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except BlockingIOError:
            return _read(fd)
        return None
    finally:
        os.close(fd)


def _read(fd: int) -> dict[str, object]:
    try:
        found = json.loads(os.pread(fd, 4096, 0) or b"{}")
    except (OSError, ValueError):
        return {}
    return found if isinstance(found, dict) else {}
