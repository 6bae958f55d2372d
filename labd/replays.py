"""The lab's own replays of records that workers elsewhere filed.

A record is *verified* when replaying it, its actions applied to the task rebuilt from
its manifest, gives back its observations bit for bit (``labd.replay``). The lab's own
workers (in its process, or its worker processes: ``labd.workers``) replay each record
they file. A worker on another machine could say anything, so the lab does not take its
word: such a worker files no verdict (the API refuses one, ``labd.api.workers``), and
the lab replays what it filed here, from the record it holds, one record at a time in a
helper process, oldest first. What a cluster's nodes ran is replayed on another of its
nodes, as many at once as the cluster has slots (``Elsewhere.parallel``). Until then
the record is "not replayed yet", and an evaluation with it is not verified (so not
ranked).

A record that cannot be replayed here gets a verdict saying why (``LabHost.replay``);
one whose replay failed for another reason (the store, a bug) is retried after the
service restarts, not in a loop.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import json
import logging
import shutil
import tempfile
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Protocol

from labd.trial import LabHost
from repository.blobs import BlobStore
from repository.index import Derived, Index
from repository.trial import Trial
from repository.well_known import RECORD_FILE, REPLAY

log = logging.getLogger("labd.replays")


class Elsewhere(Protocol):
    """Where some records are replayed instead of here: a cluster replays what its
    nodes ran on another of its nodes (``labd.cluster.Cluster``)."""

    @property
    def parallel(self) -> int:
        """How many of its replays may run at once."""
        ...

    def ran_here(self, worker: str | None) -> bool: ...
    async def replay(self, trial: Trial) -> bytes: ...


class LabReplays:
    """Replays, here, the records that untrusted workers filed, and files the verdicts."""

    def __init__(
        self,
        index: Index,
        store: BlobStore,
        host: LabHost,
        work: Path,
        trusted: Sequence[str],
        *,
        poll: float = 2.0,
        seconds: float = 1800.0,
        on_verdict: Callable[[bytes], None] | None = None,
        elsewhere: Elsewhere | None = None,
    ) -> None:
        self.index = index
        self.store = store
        self.host = host
        self.work = work
        self.trusted = tuple(trusted)  # worker-name prefixes that replay their own filings
        self.poll = poll
        self.seconds = seconds  # one replay's limit
        self.on_verdict = on_verdict
        self.elsewhere = elsewhere  # replays what a cluster's nodes ran (labd.cluster)
        self._failed: set[int] = set()
        self._running: dict[int, asyncio.Task[None]] = {}
        self._here = asyncio.Semaphore(1)  # this machine's replays: one at a time
        self._wake = asyncio.Event()
        self._loop: asyncio.AbstractEventLoop | None = None

    def wake(self, *_: object) -> None:
        """A record was filed (from any thread: the queue's ``on_filed``): look for work
        now rather than at the next poll."""
        if self._loop is not None and not self._loop.is_closed():
            self._loop.call_soon_threadsafe(self._wake.set)

    async def run(self, stop: asyncio.Event) -> None:
        """Replay records until ``stop`` is set: one at a time here, and as many at once
        as a cluster has slots for what its nodes ran."""
        self._loop = asyncio.get_running_loop()
        try:
            while not stop.is_set():
                trial_id = None
                if len(self._running) < self._room():
                    try:
                        trial_id = await asyncio.to_thread(
                            self.index.unreplayed, self.trusted, self._failed | set(self._running)
                        )
                    except Exception:  # the database away for a moment: try again later
                        log.exception("could not look for records to replay")
                if trial_id is None:  # nothing to replay, or no room: until one ends
                    self._wake.clear()
                    with contextlib.suppress(TimeoutError):
                        await asyncio.wait_for(self._wake.wait(), self.poll)
                    continue
                task = asyncio.create_task(self._replay_one(trial_id), name=f"replay {trial_id}")
                self._running[trial_id] = task
                task.add_done_callback(functools.partial(self._ended, trial_id))
        finally:
            for task in list(self._running.values()):
                task.cancel()
            for task in list(self._running.values()):
                with contextlib.suppress(asyncio.CancelledError):
                    await task

    def _room(self) -> int:
        return 1 if self.elsewhere is None else max(1, self.elsewhere.parallel)

    def _ended(self, trial_id: int, _: object) -> None:
        self._running.pop(trial_id, None)
        self._wake.set()

    async def _replay_one(self, trial_id: int) -> None:
        try:
            await self.replay(trial_id)
        except Exception:  # never let one record stop the others; it waits for a restart
            log.exception("trial %d: the lab could not replay its record", trial_id)
            self._failed.add(trial_id)

    async def replay(self, trial_id: int) -> Derived:
        """Replay trial ``trial_id``'s record here and file the verdict beside it."""
        trial = await asyncio.to_thread(self.index.trial, trial_id)
        if trial.mcap is None:
            raise ValueError(f"trial {trial_id} has no record")
        self.work.mkdir(parents=True, exist_ok=True)
        folder = Path(tempfile.mkdtemp(prefix=f"replay-{trial_id}-", dir=self.work))
        try:
            if self.elsewhere is not None and self.elsewhere.ran_here(trial.worker):
                verdict = await self.elsewhere.replay(trial)
            else:
                async with self._here:
                    mcap = await asyncio.to_thread(
                        self.store.copy_to, trial.mcap, folder / RECORD_FILE
                    )
                    done = await asyncio.to_thread(
                        self.host.replay, mcap, folder / "replay", seconds=self.seconds
                    )
                verdict = done.verdict
            path = folder / REPLAY
            path.write_bytes(verdict)
            digest = await asyncio.to_thread(self.store.put_file, path)
            item = Derived(REPLAY, digest, len(verdict), "application/json")
            await asyncio.to_thread(self.index.put_derived, trial_id, item)
            if self.on_verdict is not None:
                self.on_verdict(verdict)
            said = "verified" if json.loads(verdict).get("verified") else "did not verify"
            log.info("trial %d (worker %s): the lab's replay %s", trial_id, trial.worker, said)
            return item
        finally:
            await asyncio.to_thread(shutil.rmtree, folder, True)
