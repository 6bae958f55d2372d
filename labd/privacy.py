"""The lab's private files, and the line that says one of them is not.

The data folder, the index (password and token hashes, reservations' nonces, held-out
suites' seeds), the keys folder and the secrets in it (the signing key, the secrets
reservations' keys and held-out seeds derive from) are for the lab's user alone. The lab
makes them so where it creates them (folders 0700, files 0600: ``labd.datalock``,
``labd.service``, ``repository.index``, ``repository.signing``,
``repository.reservations``); a folder an older labd made (0755, 0644) stays as it was,
and ``labd serve`` says so, one line per path with its mode and the chmod that makes it
private. It changes no mode itself: the operator may have given a group of theirs
access on purpose, and a chmod behind their back would be a surprise either way.

What sandboxes read (a trial's code under ``DATA/work``, runtimes and pinned data under
``DATA/cache``) keeps its own modes below the private folder: Docker's engine mounts it as
root, and bubblewrap, run by a root lab, binds it where the job's uid can reach it
(``sandbox.views``), so no folder of the lab need be readable by that uid.
"""

from __future__ import annotations

import stat
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import sqlalchemy as sa

if TYPE_CHECKING:
    from labd.service import ServiceConfig

FOLDER = 0o700  # private modes, as the lab makes them
FILE = 0o600
OTHERS = 0o077  # the bits that let anyone but the owner in


@dataclass(frozen=True)
class Wide:
    """A private path others may read or enter: where, its mode, the mode it should have."""

    path: Path
    mode: int
    private: int

    def __str__(self) -> str:
        return (
            f"{self.path} is {self.mode:04o}: other users of this machine may read what"
            f" the lab keeps private there (password and token hashes, keys, held-out"
            f" seeds); make it the lab's alone: chmod {self.private:o} {self.path}"
        )


def lab_paths(config: ServiceConfig) -> tuple[Path, Path, str]:
    """The data folder, keys folder and index URL of the lab ``config`` describes."""
    return config.data, config.keys or config.data / "keys", config.database_url


def private_paths(data: Path, keys: Path, database_url: str) -> Iterator[tuple[Path, int]]:
    """The lab's private paths that exist, each with its private mode."""
    yield data, FOLDER
    database = sa.make_url(database_url).database if database_url.startswith("sqlite") else None
    if database and database != ":memory:":
        for suffix in ("", "-wal", "-shm"):  # the WAL holds rows not yet in the file
            yield Path(database + suffix), FILE
    yield keys, FOLDER
    if keys.is_dir():
        yield keys / "signing.pem", FILE
        for secret in sorted(keys.glob("*.secret")):
            yield secret, FILE


def wider(data: Path, keys: Path, database_url: str) -> list[Wide]:
    """The lab's private paths whose mode lets anyone but their owner in (one absent is
    none: the lab makes it private)."""
    found = []
    for path, private in private_paths(data, keys, database_url):
        try:
            mode = stat.S_IMODE(path.lstat().st_mode)
        except FileNotFoundError:
            continue
        if mode & OTHERS:
            found.append(Wide(path.absolute(), mode, private))
    return found
