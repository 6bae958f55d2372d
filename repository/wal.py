"""The files of a SQLite index, held open and watched while the lab serves.

SQLite keeps what was written since its last checkpoint in the write-ahead log beside
the database (``index.sqlite-wal``), indexed by a shared-memory file (``-shm``).
Deleting the WAL under a running lab loses that silently: its connections go on writing
into the deleted file, a new connection cannot read, and after a crash the index is what
it was at the last checkpoint (for a young lab, empty: every user and trial gone).

``IndexFiles`` keeps one connection open for as long as the index is (so SQLite itself
never deletes the WAL: it does so only when its last connection closes) and notes the
inode of the database, its WAL and its shared memory. ``check`` (before every write,
and for ``/readyz``) compares them with the files now at those paths. When one was
deleted or replaced, it copies what the open WAL holds into the database (a checkpoint
through the connection it kept, which still reads the deleted file), logs it, and from
then on refuses every write with ``IndexLost`` saying what happened and what to do: a
restart opens the files afresh, with nothing lost.
"""

from __future__ import annotations

import logging
import os
import sqlite3
import threading
from pathlib import Path

from repository.errors import IndexLost

log = logging.getLogger("repository.index")
SUFFIXES = ("", "-wal", "-shm")  # the database, its write-ahead log, its shared memory


class IndexFiles:
    """The files of the SQLite database at ``path``, held open and watched."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._lock = threading.Lock()
        self._keeper = sqlite3.connect(path, isolation_level=None, check_same_thread=False)
        self._keeper.execute("PRAGMA journal_mode=WAL")
        self._keeper.execute("SELECT count(*) FROM sqlite_master").fetchall()  # opens the WAL
        self._inodes = {name: _inode(self._file(name)) for name in SUFFIXES}
        self.lost: str | None = None  # why writes are refused, once they are

    def _file(self, suffix: str) -> Path:
        return self.path.with_name(self.path.name + suffix)

    def check(self) -> None:
        """Raise ``IndexLost`` if a file of the index is not the one opened (the first
        time: after saving what the open WAL holds into the database)."""
        with self._lock:
            if self.lost is None:
                changed = [
                    self._file(suffix)
                    for suffix, inode in self._inodes.items()
                    if _inode(self._file(suffix)) != inode
                ]
                if changed:
                    self.lost = self._save(changed)
            if self.lost is not None:
                raise IndexLost(self.lost)

    def _save(self, changed: list[Path]) -> str:
        names = " and ".join(str(p) for p in changed)
        try:
            self._keeper.execute("PRAGMA wal_checkpoint(TRUNCATE)").fetchall()
            saved = f"what the open log held was copied into {self.path}, so nothing is lost"
        except sqlite3.Error as err:
            saved = f"copying what the open log held into {self.path} failed ({err})"
        reason = (
            f"the archive's index is not writable: {names} was deleted or replaced while"
            f" the lab had it open; {saved}. The lab refuses writes until it is restarted:"
            " restart labd serve (and never delete or move an index's -wal or -shm file"
            " while a lab runs on it)"
        )
        log.critical("%s", reason)
        return reason

    def close(self) -> None:
        with self._lock:
            self._keeper.close()


def _inode(path: Path) -> tuple[int, int] | None:
    try:
        found = os.stat(path)
    except FileNotFoundError:
        return None
    return found.st_dev, found.st_ino
