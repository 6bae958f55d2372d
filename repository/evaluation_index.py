"""The evaluations in the index: their rows, their episodes' trials, retired suites.

An evaluation's row says what was evaluated (task and suite, both with their versions,
repository and commit); ``evaluation_episodes`` ties each episode of the suite (its
place and seed) to the trial that ran it. What an evaluation adds up to is read from
those trials whenever it is asked for (``repository.evaluation.score``), so it is never
out of step with them; when the last episode has ended the lab signs it once.

Whether an episode's replay verified is in its replay verdict, a derived blob: the
caller passes ``replayed`` (a verdict's digest -> verified), which reads the blob store.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import sqlalchemy as sa
from sqlalchemy.engine import Connection

from repository.errors import ArchiveError, RecordNotFound
from repository.evaluation import (
    EpisodeRow,
    Evaluation,
    hide,
    partiality,
    reproduced,
    score,
    status_of,
)
from repository.index import Index, spellings
from repository.tables import derived, episodes, evaluations, retired_suites, trials
from repository.trial import Order, Outcome, Status
from repository.units import moment
from repository.well_known import REPLAY

E = evaluations.c
Replayed = Callable[[str], bool | None]  # a replay verdict's blob digest -> verified


@dataclass(frozen=True)
class EvaluationFilters:
    task: str | None = None
    suite: str | None = None
    suite_version: int | None = None
    repository: str | None = None
    commit: str | None = None  # a commit, or its first digits
    submitter: str | None = None


@dataclass(frozen=True)
class EvaluationPage:
    items: list[Evaluation]
    next: int | None


class Evaluations:
    """The evaluations on ``index``."""

    def __init__(
        self,
        index: Index,
        replayed: Replayed,
        *,
        replayed_on: Callable[[str], str | None] = lambda _: None,
    ) -> None:
        self.index = index
        self.replayed = replayed
        self.replayed_on = replayed_on  # a verdict's digest -> the cluster's node it says

    def add(
        self,
        db: Connection,
        order: Order,
        *,
        task_version: str,
        suite: str,
        suite_version: int,
        held_out: bool,
        submitter: str,
        seeds: Sequence[int],
        trial_ids: Sequence[int],
        rerun_of: int | None = None,
    ) -> int:
        """Insert an evaluation of what ``order`` asked (its code, task and parameters;
        each episode's seed is one of ``seeds``) whose episodes ``trial_ids`` (in the
        suite's order, one per seed) were just queued in the transaction ``db``; its id.
        ``rerun_of``: the evaluation it reruns."""
        if len(seeds) != len(trial_ids):
            raise ArchiveError(f"{len(seeds)} seeds for {len(trial_ids)} trials")
        task = order.task
        if task is None:
            raise ArchiveError("an evaluation's order names its task")
        result = db.execute(
            sa.insert(evaluations).values(
                task=task,
                task_version=task_version,
                suite=suite,
                suite_version=suite_version,
                held_out=held_out,
                repository=order.repository,
                ref=order.ref,
                commit=order.commit,
                params=dict(order.params),
                submitter=submitter,
                rerun_of=rerun_of,
                created=self.index.clock(),
                cancel_requested=False,
            )
        )
        key = result.inserted_primary_key
        assert key is not None
        evaluation_id = int(key[0])
        hidden = held_out and not self._retired(db, task, suite, suite_version)
        db.execute(
            sa.insert(episodes),
            [
                {
                    "evaluation_id": evaluation_id,
                    "episode": n,
                    "seed": seed,
                    "trial_id": trial,
                    "hidden": hidden,
                }
                for n, (seed, trial) in enumerate(zip(seeds, trial_ids, strict=True))
            ],
        )
        return evaluation_id

    def get(self, evaluation_id: int, *, reveal: bool = False) -> Evaluation:
        """One evaluation (RecordNotFound). A held-out suite's, before its version is
        retired, is its aggregate alone (``repository.evaluation.hide``) unless
        ``reveal`` (the operator, and the lab itself when it signs or reruns it)."""
        with self.index.engine.connect() as db:
            row = db.execute(sa.select(evaluations).where(E.id == evaluation_id)).one_or_none()
            if row is None:
                raise RecordNotFound("evaluation", str(evaluation_id))
            return self._build(db, [row], reveal)[0]

    def find(
        self, filters: EvaluationFilters, *, limit: int = 50, before: int | None = None
    ) -> EvaluationPage:
        """Evaluations matching ``filters``, newest first, a page at a time."""
        query = sa.select(evaluations).where(*_conditions(filters))
        if before is not None:
            query = query.where(E.id < before)
        query = query.order_by(E.id.desc()).limit(limit + 1)
        with self.index.engine.connect() as db:
            rows = db.execute(query).all()
            more = len(rows) > limit
            items = self._build(db, rows[:limit], reveal=False)
        return EvaluationPage(items, items[-1].id if more and items else None)

    def of_suite(self, task: str, suite: str, version: int | None = None) -> list[Evaluation]:
        """Every evaluation of a task's suite (of one version, or all), oldest first."""
        conditions = [E.task == task, E.suite == suite]
        if version is not None:
            conditions.append(E.suite_version == version)
        with self.index.engine.connect() as db:
            rows = db.execute(sa.select(evaluations).where(*conditions).order_by(E.id)).all()
            return self._build(db, rows, reveal=False)

    def held_out_used(
        self,
        db: Connection,
        submitter: str,
        *,
        commit: str,
        task: str,
        suite: tuple[str, int],
        since: float,
    ) -> tuple[int, int]:
        """How many held-out evaluations ``submitter`` has: of ``commit`` on ``task``'s
        ``suite`` (name, version; those the lab broke not counted, since they were not the
        submitter's doing), and of any held-out suite since ``since``. Read in the
        transaction ``db`` that holds the submitter's lock, so two submissions at once
        cannot both take the last one."""
        broke = (
            sa.select(episodes.c.evaluation_id)
            .join(trials, trials.c.id == episodes.c.trial_id)
            .where(trials.c.lab_fault)
        )
        mine = [E.submitter == submitter, E.held_out]
        of_commit = db.execute(
            sa.select(sa.func.count())
            .select_from(evaluations)
            .where(
                *mine,
                E.commit == commit,
                E.task == task,
                E.suite == suite[0],
                E.suite_version == suite[1],
                E.id.not_in(broke),
            )
        ).scalar_one()
        lately = db.execute(
            sa.select(sa.func.count()).select_from(evaluations).where(*mine, E.created >= since)
        ).scalar_one()
        return int(of_commit), int(lately)

    def of_trial(self, trial_id: int) -> int | None:
        """The evaluation the trial is an episode of, if any."""
        with self.index.engine.connect() as db:
            return db.execute(
                sa.select(episodes.c.evaluation_id).where(episodes.c.trial_id == trial_id)
            ).scalar()

    def trials(self, evaluation_id: int) -> list[int]:
        """The trials of an evaluation's episodes, in the suite's order."""
        with self.index.engine.connect() as db:
            return list(
                db.execute(
                    sa.select(episodes.c.trial_id)
                    .where(episodes.c.evaluation_id == evaluation_id)
                    .order_by(episodes.c.episode)
                ).scalars()
            )

    def request_cancel(self, evaluation_id: int) -> None:
        with self.index.begin() as db:
            db.execute(
                sa.update(evaluations).where(E.id == evaluation_id).values(cancel_requested=True)
            )

    def sign(self, evaluation_id: int, signature: Mapping[str, Any], finished: float) -> bool:
        """Keep the lab's signature of an evaluation whose episodes have all ended; False
        if it was signed already (the first signature stays)."""
        with self.index.begin() as db:
            return (
                db.execute(
                    sa.update(evaluations)
                    .where(E.id == evaluation_id, E.signature.is_(None))
                    .values(signature=dict(signature), finished=finished)
                ).rowcount
                == 1
            )

    def retire(self, task: str, suite: str, version: int) -> int:
        """Retire a held-out suite version: its episodes are public from now on, and new
        evaluations of it too. How many episodes became public."""
        with self.index.begin() as db:
            if not self._retired(db, task, suite, version):
                db.execute(
                    sa.insert(retired_suites).values(
                        task=task, suite=suite, version=version, retired=self.index.clock()
                    )
                )
            ids = sa.select(E.id).where(
                E.task == task, E.suite == suite, E.suite_version == version
            )
            return db.execute(
                sa.update(episodes)
                .where(episodes.c.evaluation_id.in_(ids), episodes.c.hidden)
                .values(hidden=False)
            ).rowcount

    def retired(self, task: str) -> set[tuple[str, int]]:
        """The task's retired suite versions, as (suite, version)."""
        with self.index.engine.connect() as db:
            rows = db.execute(
                sa.select(retired_suites.c.suite, retired_suites.c.version).where(
                    retired_suites.c.task == task
                )
            ).all()
        return {(r.suite, r.version) for r in rows}

    def _retired(self, db: Connection, task: str, suite: str, version: int) -> bool:
        found = db.execute(
            sa.select(retired_suites.c.retired).where(
                retired_suites.c.task == task,
                retired_suites.c.suite == suite,
                retired_suites.c.version == version,
            )
        ).first()
        return found is not None

    def _build(self, db: Connection, rows: Sequence[Any], reveal: bool) -> list[Evaluation]:
        """The records of evaluation ``rows``, with their episodes (two queries for all)."""
        ids = [r.id for r in rows]
        if not ids:
            return []
        t = trials.c
        found = db.execute(
            sa.select(
                episodes.c.evaluation_id,
                episodes.c.episode,
                episodes.c.seed,
                episodes.c.hidden,
                t.id,
                t.status,
                t.outcome,
                t.reward,
                t.data_digest,
                t.wall_seconds,
                t.finished,
                t.reproduced,
                t.lab_fault,
                t.worker,
            )
            .join(trials, trials.c.id == episodes.c.trial_id)
            .where(episodes.c.evaluation_id.in_(ids))
            .order_by(episodes.c.evaluation_id, episodes.c.episode)
        ).all()
        verdicts = self._verdicts(db, [f.id for f in found])
        by_evaluation: dict[int, list[tuple[EpisodeRow, float | None]]] = {i: [] for i in ids}
        hidden = {f.evaluation_id for f in found if f.hidden}
        for f in found:
            by_evaluation[f.evaluation_id].append(
                (
                    EpisodeRow(
                        episode=f.episode,
                        trial=f.id,
                        seed=f.seed,
                        status=Status(f.status),
                        outcome=Outcome(f.outcome) if f.outcome else None,
                        reward=f.reward,
                        data_digest=f.data_digest,
                        verified=verdicts.get(f.id, (None, None))[0],
                        replayed_elsewhere=_elsewhere(f.worker, verdicts.get(f.id)),
                        compute_seconds=f.wall_seconds,
                        reproduced=f.reproduced,
                        lab_fault=f.lab_fault,
                    ),
                    f.finished,
                )
            )
        built = [_evaluation(r, by_evaluation[r.id]) for r in rows]
        return [hide(e) if e.id in hidden and not reveal else e for e in built]

    def _verdicts(
        self, db: Connection, trial_ids: Iterable[int]
    ) -> dict[int, tuple[bool | None, str | None]]:
        """Each replayed trial's verdict: verified, and the node it says it ran on."""
        ids = list(trial_ids)
        if not ids:
            return {}
        rows = db.execute(
            sa.select(derived.c.trial_id, derived.c.digest).where(
                derived.c.trial_id.in_(ids), derived.c.name == REPLAY
            )
        ).all()
        return {r.trial_id: (self.replayed(r.digest), self.replayed_on(r.digest)) for r in rows}


def _elsewhere(worker: str | None, verdict: tuple[bool | None, str | None] | None) -> bool | None:
    """Whether a replay ran on another node of the cluster than its trial (None: not
    replayed, or not by the cluster)."""
    if verdict is None or verdict[1] is None:
        return None
    return verdict[1] != worker


def _evaluation(row: Any, found: list[tuple[EpisodeRow, float | None]]) -> Evaluation:
    rows = [r for r, _ in found]
    status = status_of(rows, row.cancel_requested)
    ended = [f for _, f in found if f is not None]
    finished = row.finished
    if finished is None and ended and status.ended:
        finished = max(ended)
    partial = partiality(rows, row.cancel_requested)
    return Evaluation(
        **dict(score(rows, seed=row.id)),
        id=row.id,
        task=row.task,
        task_version=row.task_version,
        suite=row.suite,
        suite_version=row.suite_version,
        held_out=row.held_out,
        repository=row.repository,
        ref=row.ref,
        commit=row.commit,
        params=dict(row.params),
        submitter=row.submitter,
        rerun_of=row.rerun_of,
        status=status,
        partial=partial is not None,
        partial_cause=partial[0] if partial else None,
        partial_reason=partial[1] if partial else None,
        created=moment(row.created),
        finished=moment(finished) if finished is not None else None,
        rows=rows,
        reproduced=reproduced(rows) if row.rerun_of is not None else None,
        signature=row.signature,
    )


def _conditions(f: EvaluationFilters) -> list[sa.ColumnElement[bool]]:
    conditions: list[sa.ColumnElement[bool]] = []
    if f.task is not None:
        conditions.append(E.task == f.task)
    if f.suite is not None:
        conditions.append(E.suite == f.suite)
    if f.suite_version is not None:
        conditions.append(E.suite_version == f.suite_version)
    if f.repository is not None:
        conditions.append(E.repository.in_(spellings(f.repository)))
    if f.commit is not None:  # a whole commit, or its first digits (an index range)
        commit = f.commit.lower()
        if len(commit) == 40:
            conditions.append(E.commit == commit)
        else:
            conditions.append(sa.and_(E.commit >= commit, E.commit < commit + "g"))
    if f.submitter is not None:
        conditions.append(E.submitter == f.submitter)
    return conditions
