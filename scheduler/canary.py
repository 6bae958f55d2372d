"""Canary reruns: a worker checks it still reproduces the lab's reference trials.

Determinism drifts quietly: a library upgraded on one worker machine, another CPU, a
driver, and records stop reproducing before anyone notices (robomimic#230, robocasa#144
were found by users). The operator names reference trials (``--canary TRIAL``); each
worker reruns them when it starts and every ``every`` seconds, and compares each rerun's
data digest with the reference's. A canary that diverges takes that worker out of the
pool: it claims nothing more, and the lab's status (``GET /api/status``, the lab's page)
names it and the first difference, until an operator looks.
"""

from __future__ import annotations

import asyncio
import datetime as dt
import logging
import shutil
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

from repository.errors import ArchiveError
from repository.manifest import Manifest
from scheduler.errors import QueueError
from scheduler.runner import RunOptions, run_trial
from scheduler.states import State

if TYPE_CHECKING:
    from scheduler.worker import Worker

log = logging.getLogger("scheduler.canary")


@dataclass(frozen=True)
class Health:
    """A worker's state as its canaries found it."""

    worker: str
    state: State
    detail: str = ""
    since: dt.datetime = field(default_factory=lambda: dt.datetime.now(dt.UTC))


class Canaries:
    """The reference trials a worker reruns, and when it last did."""

    def __init__(
        self,
        trials: Sequence[int],
        every: float,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.trials = tuple(trials)
        self.every = every
        self.clock = clock
        self._last: float | None = None

    def due(self) -> bool:
        if not self.trials:
            return False
        return self._last is None or self.clock() - self._last >= self.every

    async def check(self, worker: Worker) -> Health:
        """Rerun every canary on ``worker``; ``out`` with the first divergence found."""
        self._last = self.clock()
        name = worker.config.name
        for trial_id in self.trials:
            try:
                problem = await self._one(worker, trial_id)
            except (ArchiveError, QueueError) as err:
                log.warning("%s: canary trial %d could not be checked: %s", name, trial_id, err)
                continue  # the lab is away, or the canary is gone: not this worker's fault
            if problem is not None:
                log.error("%s: out of the pool: %s", name, problem)
                return Health(name, State.OUT, problem)
        return Health(name, State.OK, f"{len(self.trials)} canaries reproduced")

    async def _one(self, worker: Worker, trial_id: int) -> str | None:
        reference = await asyncio.to_thread(worker.queue.trial, trial_id)
        if not reference.data_digest or not reference.mcap:
            return None  # nothing to compare with (not finished, or no record)
        order = reference.order.rerun(reference.id)
        # as the reference ran (a manifest that cannot be read: ManifestError, not checked)
        blind = Manifest.from_json(reference.manifest).blind if reference.manifest else False
        folder = Path(tempfile.mkdtemp(prefix="labd-canary-", dir=worker.config.work))
        try:
            result = await run_trial(
                order,
                blind=blind,
                backend=worker.backend,
                host=worker.host,
                out=folder / "run",
                cache=worker.config.cache,
                options=RunOptions(
                    limits=worker.config.options.limits, fetch=worker.config.options.fetch
                ),
                archive=worker.store,  # the records it learnt from, as a rerun gets them
            )
            if result.data_digest == reference.data_digest:
                return None
            if result.mcap is None:
                return f"canary trial {trial_id} made no record: {result.reason}"
            theirs = folder / "reference.mcap"
            await asyncio.to_thread(worker.store.copy_to, reference.mcap, theirs)
            topics = reference.digest_topics or result.digest_topics
            where = await asyncio.to_thread(
                worker.host.first_difference, theirs, result.mcap, topics
            )
            return f"canary trial {trial_id} did not reproduce: {where or 'the data differ'}"
        finally:
            shutil.rmtree(folder, ignore_errors=True)
