"""Submissions and reruns: from a request to a queued trial pinned to one commit.

A submission names a repository, a ref, a task, parameters and a seed. Everything is
checked before anything is written: the task and its parameters against the registry,
the repository against the fetch policy (scheme, size, time), the ref resolved to a
commit in the mirror cache. Only then is the trial queued, pinned to that commit; so a
request that fails leaves nothing behind.

A rerun queues the same repository, commit, task, parameters and seed as an earlier
trial, linked to it, so its record can say whether it reproduced.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from labd.errors import LabError
from labd.sim import registry
from repository.index import Index, User
from scheduler.errors import InvalidRequest
from scheduler.fetch import FetchPolicy, resolve
from scheduler.queue import Queue

log = logging.getLogger("scheduler.submit")
MAX_SEED = 2**63 - 1


class Submissions:
    def __init__(self, queue: Queue, cache: Path, policy: FetchPolicy) -> None:
        self.queue = queue
        self.index: Index = queue.index
        self.cache = cache
        self.policy = policy

    def submit(
        self,
        user: User,
        *,
        repository: str,
        ref: str | None,
        task: str,
        params: Mapping[str, Any] | None = None,
        seed: int = 0,
    ) -> int:
        """Check, resolve and queue; the new trial's id.

        Raises InvalidRequest, RepositoryError or QuotaExceeded, having written nothing.
        """
        given = dict(params or {})
        checked = check_task(task, given, seed)
        resolved = resolve(repository, ref, self.cache, self.policy)
        trial_id = self.queue.submit(
            user,
            repository=resolved.repository,
            ref=ref,
            commit=resolved.commit,
            task=task,
            params=checked,
            seed=seed,
            public=resolved.public,
        )
        log.info(
            "trial %d queued for %s: %s@%s (%s) %s",
            trial_id,
            user.name,
            resolved.repository,
            resolved.commit[:12],
            ref or "HEAD",
            task,
        )
        return trial_id

    def rerun(self, user: User, trial_id: int) -> int:
        """Queue a rerun of trial ``trial_id``; its id (RecordNotFound, QuotaExceeded)."""
        old = self.index.trial(trial_id)
        original = old["rerun_of"] or old["id"]  # a rerun of a rerun compares to the original
        if original != old["id"]:
            old = self.index.trial(original)
        new_id = self.queue.submit(
            user,
            repository=old["repository"],
            ref=old["commit"],
            commit=old["commit"],
            task=old["task"],
            params=old["params"],
            seed=old["seed"],
            public=old["public"],
            rerun_of=original,
        )
        log.info("trial %d queued for %s: a rerun of %d", new_id, user.name, original)
        return new_id


def check_task(task: str, given: dict[str, Any], seed: int) -> dict[str, Any]:
    """The given parameters, validated and normalized (InvalidRequest)."""
    if isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed <= MAX_SEED:
        raise InvalidRequest(f"seed {seed!r}: give an integer from 0 to {MAX_SEED}")
    try:
        values = registry.validate(task, given)
    except LabError as err:
        raise InvalidRequest(str(err)) from None
    return {name: values[name] for name in sorted(given)}
