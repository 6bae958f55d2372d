"""Submissions and reruns: from a request to a queued trial pinned to one commit.

A submission (``repository.trial.TrialRequest``) names a repository, a ref, a task,
parameters and a seed; the request model has checked their shapes. Everything else is
checked before anything is written: the task and its parameters by the lab
(``TrialHost.check``), the repository against the fetch policy (scheme, size, time),
the ref resolved to a commit in the mirror cache, and that commit's ``lab.toml``, read
as ``labd run`` reads it (a missing or broken one is refused with the same message; the
task, when the request names none, is the one it names). Only then is the trial
queued, pinned to that commit; so a request that fails leaves nothing behind.

All of it happens while the submitter waits, so it runs within the fetch policy's
``resolve_timeout`` (a git server that never answers holds a submission that long, no
longer), and ``submit_async`` runs it in a pool of threads of its own: at most
``threads`` submissions are resolved at once and ``waiting`` more wait their turn;
past that a submission is refused at once (``Busy``). So submissions, however slow
their servers, never take the threads that answer the archive's readers.

When ``lab.toml`` has ``[data]``, it is resolved here against the archive
(``scheduler.data``): the trial is queued with the fixed list of records it learns
from, which the answer shows.

A rerun queues the same repository, commit, task, parameters, seed and pinned data as
an earlier trial, linked to it, so its record can say whether it reproduced.
"""

from __future__ import annotations

import asyncio
import logging
import tempfile
import threading
from collections.abc import Callable, Mapping
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

from repository.index import Index, User
from repository.trial import Kind, Order, PinnedRecord, TrialRequest
from scheduler import controller
from scheduler import data as pinning
from scheduler.data import Archive, DataPolicy
from scheduler.errors import Busy, InvalidRequest
from scheduler.fetch import FetchPolicy, Resolved, resolve, submitting
from scheduler.host import TrialHost
from scheduler.queue import Queue
from scheduler.source import checkout

R = TypeVar("R")
log = logging.getLogger("scheduler.submit")


@dataclass(frozen=True)
class Prepared:
    """A submission checked and resolved: the order its trials are queued with (one per
    seed for an evaluation: ``Order.episode``)."""

    order: Order
    tasks: tuple[str, ...] = ()  # the tasks lab.toml says the code supports (none: any)

    def __str__(self) -> str:
        order = self.order
        where = f"{order.repository}@{order.commit[:12]} ({order.ref or 'HEAD'})"
        return f"{where} {order.task}"


class Submissions:
    def __init__(
        self,
        queue: Queue,
        host: TrialHost,
        cache: Path,
        policy: FetchPolicy,
        *,
        archive: Archive | None = None,
        data_policy: DataPolicy | None = None,
        threads: int = 8,
        waiting: int = 32,
    ) -> None:
        self.queue = queue
        self.host = host
        self.index: Index = queue.index
        self.cache = cache
        self.policy = submitting(policy)  # the submitter waits: the shorter deadline
        self.archive = archive  # where [data] is resolved; None: refused
        self.data_policy = data_policy or DataPolicy()
        self.threads = threads
        self.waiting = waiting
        self._pool = ThreadPoolExecutor(threads, thread_name_prefix="labd-submit")
        self._lock = threading.Lock()
        self._in_hand = 0  # submissions running or waiting in the pool

    async def submit_async(self, user: User, request: TrialRequest) -> int:
        """``submit`` in this lab's own pool of threads (``in_pool``)."""
        return await self.in_pool(self.submit, user, request)

    async def in_pool(self, call: Callable[..., R], *args: Any) -> R:
        """``call(*args)`` (a submission: it resolves a ref, so it may wait on a git
        server) in this lab's own pool of threads; ``Busy`` at once when the pool has as
        many submissions in hand as it takes.

        A submission whose caller stops waiting (a client gone) still ends in the pool,
        and counts until it has: leaving does not make room for more.
        """
        with self._lock:
            if self._in_hand >= self.threads + self.waiting:
                raise Busy(self._in_hand, retry_after=max(1.0, self.policy.timeout / 2))
            self._in_hand += 1
        try:
            future = self._pool.submit(call, *args)
        except BaseException:
            self._release()
            raise
        future.add_done_callback(self._release)
        return await asyncio.wrap_future(future)

    def _release(self, _: Future[Any] | None = None) -> None:
        with self._lock:
            self._in_hand -= 1

    def close(self) -> None:
        """Drop the submissions still waiting; those running end at their deadline."""
        self._pool.shutdown(wait=False, cancel_futures=True)

    def submit(self, user: User, request: TrialRequest) -> int:
        """Check, resolve and queue; the new trial's id.

        Raises InvalidRequest, RepositoryError or QuotaExceeded, having written nothing.
        """
        prepared = self.prepare(request.repository, request.ref, request.task, request.params)
        order = prepared.order.episode(request.seed)
        trial_id = self.queue.submit(user, order)
        log.info(
            "trial %d queued for %s: %s, learning from %s",
            trial_id,
            user.name,
            prepared,
            f"trials {', '.join(str(p.trial) for p in order.data)}" if order.data else "no data",
        )
        return trial_id

    def prepare(
        self, repository: str, ref: str | None, task: str | None, params: Mapping[str, Any]
    ) -> Prepared:
        """Check the task and parameters, resolve the ref to a commit, read its
        ``lab.toml`` and pin its ``[data]``: the order a trial of it is queued with (its
        seed 0: ``Order.episode`` sets it).

        Raises InvalidRequest or RepositoryError.
        """
        if task is not None:  # a wrong task or parameter is refused before fetching
            self.host.check(task, params)
        resolved = resolve(repository, ref, self.cache, self.policy)
        config = self.lab_toml(resolved)
        task = task or config.task
        if task is None:
            tasks = ", ".join(self.host.tasks())
            raise InvalidRequest(
                f"{controller.FILE} names no task, and the request gives none: name one"
                f" (--task, or task in {controller.FILE}); the tasks are {tasks}"
            )
        values = self.host.check(task, params)
        data: list[PinnedRecord] = []
        if config.data is not None:
            if self.archive is None:
                raise InvalidRequest(f"{controller.FILE} has [data], but this lab has no archive")
            data = pinning.resolve(config.data, self.archive, self.data_policy)
        return Prepared(
            Order(
                repository=resolved.repository,
                ref=ref,
                commit=resolved.commit,
                task=task,
                params={name: values[name] for name in sorted(params)},  # as normalized
                public=resolved.public,
                data=tuple(data),
            ),
            config.tasks,
        )

    def lab_toml(self, resolved: Resolved) -> controller.ControllerConfig:
        """The commit's ``lab.toml``, checked as a trial checks it (``TrialError``)."""
        with tempfile.TemporaryDirectory(prefix="labd-submit-") as folder:
            code = Path(folder) / "code"
            checkout(resolved.repository, resolved.commit, code, self.cache, self.policy)
            return controller.load(code)

    def rerun(self, user: User, trial_id: int) -> int:
        """Queue a rerun of trial ``trial_id``; its id (RecordNotFound, QuotaExceeded).

        A rerun of a rerun is a rerun of the original, so every verdict compares with
        the same record.
        """
        old = self.index.readable(trial_id)
        if old.kind is Kind.DEMONSTRATION:
            raise InvalidRequest(
                f"trial {trial_id} is a demonstration, a person's live drive: it has no code"
                f" to rerun; replay it instead (labd replay {trial_id})"
            )
        if old.rerun_of is not None:
            old = self.index.trial(old.rerun_of)
        # the very records it learnt from, whatever was filed since
        new_id = self.queue.submit(user, old.order.rerun(old.id))
        log.info("trial %d queued for %s: a rerun of %d", new_id, user.name, old.id)
        return new_id
