"""Exports being built for the API: each built once, however many ask for it at once,
and one at a time.

An export takes seconds of CPU (its camera images are rendered by replaying each
record), and anyone may ask for any export. So each export is kept once built (one
trial's in the blob store beside its record, ``labd.api.records``; many trials' as a
file here, under ``DATA/exports``), a request for an export being built waits for that
build rather than starting another, ``BUILDS`` builds run at once, and ``WAITING``
more may wait their turn: past that, a request is refused with a 503 to retry later,
so that no crowd of different exports can queue up hours of work.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import logging
import os
import shutil
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

import anyio
import anyio.to_thread

from labd.api.errors import ApiError
from repository.units import GiB

log = logging.getLogger("labd.api.builds")
T = TypeVar("T")
BUILDS = 1  # exports built at once
WAITING = 8  # different exports waiting for their build, past those being built
KEEP_BYTES = GiB  # many-trial exports kept on disk, the least recently used dropped past this


class Builds:
    """The API's export builds under way, and the many-trial exports kept in ``folder``.

    Used on the API's event loop (``once``) and from threads (``kept``, ``keep``).
    """

    def __init__(
        self,
        folder: Path,
        *,
        builds: int = BUILDS,
        waiting: int = WAITING,
        keep_bytes: int = KEEP_BYTES,
    ) -> None:
        self.folder = folder
        self.builds = builds
        self.waiting = waiting
        self.keep_bytes = keep_bytes
        self.made = 0  # builds finished, for the log and the tests
        self._running: dict[str, asyncio.Future[Any]] = {}
        self._limiter = anyio.CapacityLimiter(builds)

    async def once(self, key: str, build: Callable[[], T]) -> T:
        """What ``build()`` makes, built on a thread unless a build of ``key`` is under
        way already, in which case its result (or its error) is this one's too."""
        running = self._running.get(key)
        if running is None:
            if len(self._running) >= self.builds + self.waiting:
                raise ApiError(
                    503,
                    f"the lab is building {len(self._running)} exports, as many as it takes"
                    " at once; retry in a minute",
                )
            running = asyncio.ensure_future(self._build(key, build))
            self._running[key] = running
            running.add_done_callback(functools.partial(self._done, key))
        result: T = await asyncio.shield(running)
        return result

    async def _build(self, key: str, build: Callable[[], T]) -> T:
        began = time.monotonic()
        made = await anyio.to_thread.run_sync(build, limiter=self._limiter)
        self.made += 1
        log.info("built export %s in %.1f s", key, time.monotonic() - began)
        return made

    def _done(self, key: str, running: asyncio.Future[Any]) -> None:
        del self._running[key]
        if not running.cancelled():
            running.exception()  # retrieved here; the requests that waited raise it

    # -- many-trial exports on disk ---------------------------------------------------

    def kept(self, key: str) -> Path | None:
        """The export kept under ``key``, if there is one (marked as just used)."""
        path = self.folder / f"{key}.zip"
        try:
            os.utime(path)
        except FileNotFoundError:
            return None
        return path

    def keep(self, key: str, made: Path) -> Path:
        """Keep the file ``made`` as the export under ``key`` (moved: ``scratch`` is on
        the same disk); exports least recently used are dropped past ``keep_bytes``."""
        path = self.folder / f"{key}.zip"
        shutil.move(made, path)
        self._trim(keeping=path)
        return path

    def scratch(self) -> Path:
        """A new folder to build an export in, removed by the caller."""
        self.folder.mkdir(parents=True, exist_ok=True)
        return Path(tempfile.mkdtemp(prefix="building-", dir=self.folder))

    def _trim(self, keeping: Path) -> None:
        kept = []
        for path in self.folder.glob("*.zip"):
            with contextlib.suppress(FileNotFoundError):
                stat = path.stat()
                kept.append((stat.st_mtime, stat.st_size, path))
        total = sum(size for _, size, _ in kept)
        for _, size, path in sorted(kept):
            if total <= self.keep_bytes:
                break
            if path != keeping:
                path.unlink(missing_ok=True)
                total -= size
