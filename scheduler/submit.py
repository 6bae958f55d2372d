"""Submissions and reruns: from a request to a queued trial pinned to one commit.

A submission (``repository.trial.TrialRequest``) names a repository, a ref, a task,
parameters and a seed; the request model has checked their shapes. Everything else is
checked before anything is written: the task and its parameters by the lab
(``TrialHost.check``), the repository against the fetch policy (scheme, size, time),
the ref resolved to a commit in the mirror cache. Only then is the trial queued,
pinned to that commit; so a request that fails leaves nothing behind.

A rerun queues the same repository, commit, task, parameters and seed as an earlier
trial, linked to it, so its record can say whether it reproduced.
"""

from __future__ import annotations

import logging
from pathlib import Path

from repository.index import Index, User
from repository.trial import TrialRequest
from scheduler.fetch import FetchPolicy, resolve
from scheduler.host import TrialHost
from scheduler.queue import Queue

log = logging.getLogger("scheduler.submit")


class Submissions:
    def __init__(self, queue: Queue, host: TrialHost, cache: Path, policy: FetchPolicy) -> None:
        self.queue = queue
        self.host = host
        self.index: Index = queue.index
        self.cache = cache
        self.policy = policy

    def submit(self, user: User, request: TrialRequest) -> int:
        """Check, resolve and queue; the new trial's id.

        Raises InvalidRequest, RepositoryError or QuotaExceeded, having written nothing.
        """
        values = self.host.check(request.task, request.params)
        params = {name: values[name] for name in sorted(request.params)}  # as normalized
        resolved = resolve(request.repository, request.ref, self.cache, self.policy)
        trial_id = self.queue.submit(
            user,
            repository=resolved.repository,
            ref=request.ref,
            commit=resolved.commit,
            task=request.task,
            params=params,
            seed=request.seed,
            public=resolved.public,
        )
        log.info(
            "trial %d queued for %s: %s@%s (%s) %s",
            trial_id,
            user.name,
            resolved.repository,
            resolved.commit[:12],
            request.ref or "HEAD",
            request.task,
        )
        return trial_id

    def rerun(self, user: User, trial_id: int) -> int:
        """Queue a rerun of trial ``trial_id``; its id (RecordNotFound, QuotaExceeded).

        A rerun of a rerun is a rerun of the original, so every verdict compares with
        the same record.
        """
        old = self.index.trial(trial_id)
        if old.rerun_of is not None:
            old = self.index.trial(old.rerun_of)
        new_id = self.queue.submit(
            user,
            repository=old.repository,
            ref=old.commit,
            commit=old.commit,
            task=old.task,
            params=old.params,
            seed=old.seed,
            public=old.public,
            rerun_of=old.id,
        )
        log.info("trial %d queued for %s: a rerun of %d", new_id, user.name, old.id)
        return new_id
