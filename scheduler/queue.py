"""The persistent queue of trials, on the archive's index.

A trial is queued when submitted and goes queued → running → finished (with its
outcome) or cancelled (``repository.trial``). Workers *claim* the next trial with a
lease they renew by heartbeat; a trial whose lease ran out (its worker died, or ``labd
serve`` was killed) goes back to the queue, up to ``max_attempts`` times, so nothing
submitted is lost.

Which trial is next:

1. public repositories before private ones (the rosjs authors' policy: work that
   everyone can read and rerun goes first);
2. fair share: the submitter with the fewest trials running, so one user's hundred
   submissions do not starve another's one;
3. the oldest.

A submitter at their limit of running trials waits; their daily limit is checked at
submission. Every change is one conditional UPDATE (``WHERE status = 'queued'`` or
``WHERE worker = me``), so two workers never hold the same trial, on SQLite as on
PostgreSQL, and a late worker cannot overwrite what the queue already decided.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, TypeVar

import sqlalchemy as sa
from sqlalchemy.engine import Connection

from repository.index import Derived, Index, User, blind, hidden, reward_of, to_trial
from repository.signing import Keyring, record_statement
from repository.tables import episodes, match_legs
from repository.tables import trials as T
from repository.trial import Claim, Filing, Order, Outcome, Status, Trial
from scheduler.canary import Health
from scheduler.errors import (
    EpisodeOfEvaluation,
    FilingRefused,
    LegOfMatch,
    NotYours,
    QuotaExceeded,
)
from scheduler.states import Cancel

log = logging.getLogger("scheduler.queue")
DAY = 86400.0
# Holds a worker's filing to its record before anything is stored: (trial, filing, the
# trial it reruns) -> None, or FilingRefused (``scheduler.filing.FilingCheck``).
Check = Callable[[Trial, Filing, Trial | None], None]


@dataclass(frozen=True)
class QueueConfig:
    lease: float = 30.0  # seconds a claim lasts without a heartbeat
    max_attempts: int = 3  # claims a trial gets before it fails as lost


QUEUED, RUNNING = Status.QUEUED.value, Status.RUNNING.value
R = TypeVar("R")


class Queue:
    """The queue over ``index``; with a ``keyring``, every filed record is signed, and
    with a ``check``, every worker's filing is first held to its record."""

    def __init__(
        self,
        index: Index,
        config: QueueConfig | None = None,
        keyring: Keyring | None = None,
        check: Check | None = None,
    ) -> None:
        self.index = index
        self.config = config or QueueConfig()
        self.keyring = keyring
        self.check = check
        self.clock = index.clock
        self.health: dict[str, Health] = {}  # what each worker last said of itself
        # When each worker last claimed, renewed a lease or reported (``clock``): which
        # workers are alive, for ``/readyz`` and the metrics (``labd.health``).
        self.seen: dict[str, float] = {}
        # Called with a trial's id once it has ended (finished or cancelled), after its
        # transaction: an evaluation signs itself when its last episode has ended.
        self.on_ended: list[Callable[[int], None]] = []
        # Called after a worker's filing is stored, and after a derived artifact is
        # kept (the lab's metrics: trials' wall time, replay verdicts).
        self.on_filed: list[Callable[[int, Filing], None]] = []
        self.on_derived: list[Callable[[int, Derived], None]] = []

    # -- submitting ---------------------------------------------------------------------

    def submit(self, user: User, order: Order) -> int:
        """Queue ``order`` for ``user``, within their daily limit (QuotaExceeded); the new
        trial's id."""
        return self.submit_many(user, [order], then=lambda _db, ids: ids[0])

    def submit_many(
        self,
        user: User,
        orders: Sequence[Order],
        *,
        then: Callable[[Connection, list[int]], R],
    ) -> R:
        """Queue one trial per order for ``user``, all or none: each counts towards their
        daily limit (QuotaExceeded). ``then(db, ids)`` runs in the same transaction (an
        evaluation is written with its episodes, an order each: ``Order.episode``, and
        for a rerun ``Order.rerun`` of each episode's own); what it returns is returned."""
        with self.index.begin() as db:
            _lock_user(db, user.name)
            since = self.clock() - DAY
            today = db.execute(
                sa.select(sa.func.count())
                .select_from(T)
                .where(T.c.submitter == user.name, T.c.created >= since)
            ).scalar_one()
            if today + len(orders) > user.max_daily:
                over = (
                    f"; these {len(orders)} would take it past the daily limit of {user.max_daily}"
                    if len(orders) > 1
                    else ", the daily limit"
                )
                raise QuotaExceeded(
                    f"{user.name} has submitted {today} trials in the last 24 hours{over};"
                    " try again later or ask the operator for more"
                )
            ids = [self.index.add_trial(order, submitter=user.name, db=db) for order in orders]
            return then(db, ids)

    def _ended(self, trial_ids: Sequence[int]) -> None:
        for trial_id in trial_ids:
            _call(self.on_ended, trial_id)

    def cancel(self, trial_id: int, user: User, *, whole: bool = False) -> Cancel:
        """Cancel a queued trial now, or ask the worker of a running one to stop.

        Says what it did: ``cancelled`` (it was queued), ``stopping`` (it runs, and stops
        at its worker's next heartbeat) or ``ended`` (it had ended: nothing to do). Only
        the submitter may cancel (``NotYours``); an evaluation's episode only with its
        evaluation (``EpisodeOfEvaluation``), a match's leg only with its match
        (``LegOfMatch``; ``whole``: cancelled with it), before anything about it is
        read; ``RecordNotFound`` if there is no such trial.
        """
        if not whole:
            with self.index.engine.connect() as db:
                evaluation = db.execute(
                    sa.select(episodes.c.evaluation_id).where(episodes.c.trial_id == trial_id)
                ).scalar()
                match = db.execute(
                    sa.select(match_legs.c.match_id).where(match_legs.c.trial_id == trial_id)
                ).scalar()
            if evaluation is not None:
                raise EpisodeOfEvaluation(trial_id, evaluation)
            if match is not None:
                raise LegOfMatch(trial_id, match)
        trial = self.index.trial(trial_id)
        if trial.submitter != user.name:
            raise NotYours(trial_id, trial.submitter, "cancel")
        with self.index.begin() as db:
            cancelled = db.execute(
                sa.update(T)
                .where(T.c.id == trial_id, T.c.status == QUEUED)
                .values(
                    status=Status.CANCELLED.value,
                    reason=f"cancelled by {user.name} before it ran",
                    finished=self.clock(),
                )
            ).rowcount
            stopping = 0
            if not cancelled:
                stopping = db.execute(
                    sa.update(T)
                    .where(T.c.id == trial_id, T.c.status == RUNNING)
                    .values(cancel_requested=True)
                ).rowcount
        if cancelled:
            self._ended([trial_id])
            return Cancel.CANCELLED
        return Cancel.STOPPING if stopping else Cancel.ENDED

    # -- workers ------------------------------------------------------------------------

    def claim(self, worker: str) -> Claim | None:
        """Take the next trial for ``worker``, or None when nothing may run now.

        On PostgreSQL the candidates are locked with ``FOR UPDATE SKIP LOCKED``, so
        workers claiming at once each take a different trial without waiting; on
        SQLite, writers take turns anyway. Either way the UPDATE is conditional on the
        trial still being queued.
        """
        self.seen[worker] = self.clock()
        self.requeue_expired()
        for _ in range(5):  # another worker may take the chosen trial first
            now = self.clock()
            with self.index.begin() as db:
                candidates = self._choose(db)
                if db.dialect.name == "postgresql":  # the best one no one else is taking
                    first = next((c for c in candidates if _lock_row(db, c[0])), None)
                    candidates = [first] if first else []
                if not candidates:
                    return None
                chosen, submitter, limit = candidates[0]
                if _lock_user(db, submitter) and _running(db, submitter) >= limit:
                    continue  # another worker just gave this submitter their last slot
                taken = db.execute(
                    sa.update(T)
                    .where(T.c.id == chosen, T.c.status == QUEUED)
                    .values(
                        status=RUNNING,
                        reason="running",
                        worker=worker,
                        started=now,
                        lease_until=now + self.config.lease,
                        attempts=T.c.attempts + 1,
                    )
                ).rowcount
                if taken != 1:
                    continue
                row = db.execute(sa.select(T).where(T.c.id == chosen)).one()
                original = row.rerun_of if row.rerun_of is not None else row.id
                unseen = db.execute(
                    sa.select(sa.or_(blind(sa.literal(row.id)), blind(sa.literal(original))))
                ).scalar()
            log.info("worker %s claimed trial %d (attempt %d)", worker, chosen, row.attempts)
            return Claim(
                id=row.id, attempt=row.attempts, order=to_trial(row).order, blind=bool(unseen)
            )
        return None

    def _choose(self, db: Connection) -> list[tuple[int, str, int]]:
        """The queued trials that may run now, best first (one per submitter and kind)."""
        heads = db.execute(
            sa.select(T.c.submitter, T.c.public, sa.func.min(T.c.id))
            .where(T.c.status == QUEUED)
            .group_by(T.c.submitter, T.c.public)
        ).all()
        if not heads:
            return []
        running: dict[str, int] = dict(
            db.execute(
                sa.select(T.c.submitter, sa.func.count())
                .where(T.c.status == RUNNING)
                .group_by(T.c.submitter)
            ).all()
        )
        users = self.index.users
        names = {h[0] for h in heads}
        limits = dict(
            db.execute(
                sa.select(users.c.name, users.c.max_running).where(users.c.name.in_(names))
            ).all()
        )
        ready = sorted(
            (not public, running.get(name, 0), first, name)
            for name, public, first in heads
            if running.get(name, 0) < limits.get(name, 1)
        )
        return [(first, name, limits.get(name, 1)) for _, _, first, name in ready]

    def heartbeat(self, trial_id: int, worker: str) -> bool:
        """Renew the lease; False if the trial is no longer this worker's or must stop."""
        self.seen[worker] = self.clock()
        with self.index.begin() as db:
            renewed = db.execute(
                sa.update(T)
                .where(T.c.id == trial_id, T.c.worker == worker, T.c.status == RUNNING)
                .values(lease_until=self.clock() + self.config.lease)
            ).rowcount
            if renewed != 1:
                return False
            stop = db.execute(sa.select(T.c.cancel_requested).where(T.c.id == trial_id)).scalar()
        return not stop

    def finish(
        self, trial_id: int, worker: str, filing: Filing, *, ran_on: str | None = None
    ) -> bool:
        """Store the ending of a trial this worker holds; False if it lost the lease.
        ``ran_on`` names the worker that ran it instead, in the same transaction: a
        dispatcher claims a trial and learns only once it ran which node of a cluster
        ran it (``labd.cluster``).

        With a ``check``, the filing is first held to the record it names, outside any
        transaction (reading a record takes a while): ``FilingRefused`` if the record
        does not bear it out, and then nothing is stored or signed.
        """
        if self.check is not None:
            trial = self.index.trial(trial_id)
            if trial.worker != worker or trial.status is not Status.RUNNING:
                log.warning(
                    "worker %s finished trial %d after losing it; dropped", worker, trial_id
                )
                return False
            original = self.index.trial(trial.rerun_of) if trial.rerun_of is not None else None
            try:
                self.check(trial, filing, original)
            except FilingRefused as err:
                log.warning("worker %s: %s", worker, err)
                raise
        values = filing.model_dump(mode="json")
        values["finished"] = self.clock()
        values["reward"] = reward_of(filing.metrics)
        with self.index.begin() as db:
            done = db.execute(
                sa.update(T)
                .where(T.c.id == trial_id, T.c.worker == worker, T.c.status == RUNNING)
                .values(lease_until=None, worker=ran_on or worker, **values)
            ).rowcount
            if done == 1:
                self._sign(db, trial_id)
        if done != 1:
            log.warning("worker %s finished trial %d after losing it; dropped", worker, trial_id)
            return False
        _call(self.on_filed, trial_id, filing)
        self._ended([trial_id])
        return True

    def file_finished(
        self, order: Order, *, submitter: str, filing: Filing, started: float | None = None
    ) -> int:
        """File a record made outside the queue (a live robot's demonstration, ``order``):
        a trial that is finished when it is added, signed as any other."""
        now = self.clock()
        with self.index.begin() as db:
            trial_id = self.index.add_trial(order, submitter=submitter, db=db)
            values = filing.model_dump(mode="json")
            db.execute(
                sa.update(T)
                .where(T.c.id == trial_id)
                .values(
                    started=started if started is not None else now,
                    finished=now,
                    reward=reward_of(filing.metrics),
                    **values,
                )
            )
            self._sign(db, trial_id)
        return trial_id

    def _sign(self, db: Connection, trial_id: int) -> None:
        """Sign the trial's record as it now stands in the index (with a keyring)."""
        if self.keyring is None:
            return
        row = db.execute(sa.select(T).where(T.c.id == trial_id)).one()
        signed = self.keyring.sign(
            record_statement(
                trial=trial_id,
                kind=row.kind,
                repository=row.repository,
                commit=row.commit,
                task=row.task,
                seed=row.seed,
                status=row.status,
                outcome=row.outcome,
                manifest_digest=row.manifest_digest,
                data_digest=row.data_digest,
                digest_topics=row.digest_topics,
                mcap=row.mcap,
                mcap_size=row.mcap_size,
                metrics=row.metrics,
                finished=row.finished,
            )
        )
        db.execute(sa.update(T).where(T.c.id == trial_id).values(signature=signed.to_json()))

    def derive(self, trial_id: int, worker: str, item: Derived) -> bool:
        """Keep a derived artifact (a page summary) of a trial this worker filed; False
        if the trial is not one this worker finished."""
        trial = self.index.trial(trial_id)
        if trial.worker != worker or trial.status is not Status.FINISHED or not trial.mcap:
            log.warning(
                "worker %s filed %s for trial %d, not its own; dropped", worker, item.name, trial_id
            )
            return False
        self.index.put_derived(trial_id, item)
        _call(self.on_derived, trial_id, item)
        return True

    def requeue_expired(self) -> list[int]:
        """Put running trials whose lease ran out back in the queue (or fail them)."""
        now = self.clock()
        with self.index.begin() as db:
            lost = db.execute(
                sa.select(T.c.id, T.c.worker, T.c.attempts, T.c.cancel_requested).where(
                    T.c.status == RUNNING, T.c.lease_until < now
                )
            ).all()
            gone: list[int] = []  # ended, not requeued
            for trial_id, worker, attempts, cancel in lost:
                values: dict[str, Any]
                if cancel:
                    values = {
                        "status": Status.CANCELLED.value,
                        "reason": "cancelled; its worker was lost",
                    }
                elif attempts >= self.config.max_attempts:
                    values = {
                        "status": Status.FINISHED.value,
                        "outcome": Outcome.ERROR.value,
                        "reason": f"its worker was lost {attempts} times; the lab gave up",
                        "lab_fault": True,
                    }
                else:
                    values = {"status": QUEUED, "reason": f"requeued: worker {worker} was lost"}
                ended = values["status"] != QUEUED
                db.execute(
                    sa.update(T)
                    .where(T.c.id == trial_id, T.c.status == RUNNING, T.c.lease_until < now)
                    .values(
                        worker=None,
                        lease_until=None,
                        finished=now if ended else None,
                        started=None if not ended else T.c.started,
                        **values,
                    )
                )
                log.warning("trial %d: lease of worker %s ran out: %s", trial_id, worker, values)
                if ended:
                    gone.append(trial_id)
        self._ended(gone)
        return [row[0] for row in lost]

    def running_workers(self) -> set[str]:
        """The workers holding running trials."""
        with self.index.engine.connect() as db:
            rows = db.execute(
                sa.select(T.c.worker).where(T.c.status == RUNNING).group_by(T.c.worker)
            ).all()
        return {r[0] for r in rows if r[0]}

    def report(self, health: Health) -> None:
        """Keep what a worker says of its health (its canaries), for the lab's status."""
        self.seen[health.worker] = self.clock()
        self.health[health.worker] = health

    def running(self, *, public: bool = False) -> list[Trial]:
        """The trials running now, oldest first: who runs them and since when.
        ``public``: as everyone may see them, without held-out episodes (when each starts
        and ends would time it)."""
        query = sa.select(T).where(T.c.status == RUNNING, *_shown(public)).order_by(T.c.id)
        with self.index.engine.connect() as db:
            rows = db.execute(query).all()
        return [to_trial(r) for r in rows]

    def queued(self, *, public: bool = False) -> int:
        """How many trials wait for a worker (``public``: held-out episodes left out)."""
        with self.index.engine.connect() as db:
            count = db.execute(
                sa.select(sa.func.count())
                .select_from(T)
                .where(T.c.status == QUEUED, *_shown(public))
            ).scalar_one()
        return int(count)

    def queued_before(self, trial_id: int) -> int:
        """How many trials submitted before ``trial_id`` still wait for a worker, held-out
        episodes left out (this is shown to everyone)."""
        with self.index.engine.connect() as db:
            count = db.execute(
                sa.select(sa.func.count())
                .select_from(T)
                .where(T.c.status == QUEUED, T.c.id < trial_id, *_shown(True))
            ).scalar_one()
        return int(count)

    def trial(self, trial_id: int) -> Trial:
        """A trial's record (a worker compares a rerun with its original)."""
        return self.index.trial(trial_id)

    def release_worker(self, worker_prefix: str) -> list[int]:
        """Requeue the running trials of workers named ``worker_prefix*`` (a restart)."""
        with self.index.begin() as db:
            rows = db.execute(
                sa.select(T.c.id).where(
                    T.c.status == RUNNING, T.c.worker.startswith(worker_prefix, autoescape=True)
                )
            ).all()
            ids = [r[0] for r in rows]
            if ids:
                db.execute(
                    sa.update(T)
                    .where(T.c.id.in_(ids), T.c.status == RUNNING)
                    .values(lease_until=self.clock() - 1)
                )
        if ids:
            self.requeue_expired()
        return ids


def _call(hooks: Sequence[Callable[..., None]], trial_id: int, *more: Any) -> None:
    """Call each hook with the trial's id (and ``more``) after what it follows is stored."""
    for call in hooks:
        try:
            call(trial_id, *more)
        except Exception:  # a hook's bug must not undo the filing that called it
            log.exception("trial %d: after it was filed or ended, %s failed", trial_id, call)


def _shown(public: bool) -> list[sa.ColumnElement[bool]]:
    """The condition that leaves held-out episodes out of what everyone sees."""
    return [~hidden(T.c.id)] if public else []


def _lock_user(db: Connection, name: str) -> bool:
    """On PostgreSQL, hold a lock on this submitter's quota until the transaction ends.

    Counting a submitter's trials and then adding one must not interleave with another
    transaction doing the same, or both could pass a limit that only one may. SQLite
    needs nothing: its write transactions already run one at a time. True if locked.
    """
    if db.dialect.name != "postgresql":
        return False
    db.execute(sa.text("SELECT pg_advisory_xact_lock(hashtext(:key))"), {"key": f"labd:{name}"})
    return True


def _running(db: Connection, name: str) -> int:
    count = db.execute(
        sa.select(sa.func.count()).where(T.c.submitter == name, T.c.status == RUNNING)
    ).scalar_one()
    return int(count)


def _lock_row(db: Connection, trial_id: int) -> bool:
    """Lock a queued trial's row unless another transaction holds it (then False at once)."""
    locked = db.execute(
        sa.select(T.c.id)
        .where(T.c.id == trial_id, T.c.status == QUEUED)
        .with_for_update(skip_locked=True)
    ).first()
    return locked is not None
