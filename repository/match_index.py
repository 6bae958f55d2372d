"""The matches in the index: their rows, their legs' trials, a task's ladder.

A match's row says who plays (commits A and B, pinned) what (task, version,
parameters); ``match_legs`` ties each leg (its place, seed and who played home) to the
trial that played it. What a match adds up to is read from those trials whenever it is
asked for (``repository.match``), so it is never out of step with them; once the last
leg has ended the lab signs it once.

Whether a leg's replay verified is in its replay verdict, a derived blob: the caller
passes ``replayed`` (a verdict's digest -> verified), which reads the blob store.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import sqlalchemy as sa
from sqlalchemy.engine import Connection

from repository.errors import ArchiveError, RecordNotFound
from repository.index import Index, spellings
from repository.match import (
    LadderEntry,
    LadderRow,
    LegRow,
    Match,
    Team,
    ladder_of,
    score_of,
    status_of,
    verified_of,
)
from repository.tables import derived, ladder_entries, match_legs, matches, trials
from repository.trial import Kind, Order, Outcome, Status, TeamRef
from repository.units import moment
from repository.well_known import REPLAY

M = matches.c
Replayed = Callable[[str], bool | None]  # a replay verdict's blob digest -> verified
# a task -> its sides, home first (none for a task no longer on this lab: its legs keep
# no result)
Sides = Callable[[str], Sequence[str]]


@dataclass(frozen=True)
class MatchFilters:
    task: str | None = None
    repository: str | None = None  # either team's
    commit: str | None = None  # either team's, or its first digits
    submitter: str | None = None


@dataclass(frozen=True)
class MatchPage:
    items: list[Match]
    next: int | None


def leg_orders(
    a: Order, b: TeamRef, seeds: Sequence[int], step_deadline: float
) -> list[tuple[int, Team, Order]]:
    """The legs of a match of ``a`` (its code, task, parameters; resolved) against
    ``b``: each seed twice, A at home then B at home; (seed, home, order) each."""
    b_order = a.model_copy(update={"repository": b.repository, "ref": b.ref, "commit": b.commit})
    a_team = TeamRef(repository=a.repository, ref=a.ref, commit=a.commit)
    leg = {"kind": Kind.MATCH, "step_deadline": step_deadline}
    legs: list[tuple[int, Team, Order]] = []
    for seed in seeds:
        legs.append((seed, "a", a.model_copy(update={**leg, "seed": seed, "away": b})))
        legs.append((seed, "b", b_order.model_copy(update={**leg, "seed": seed, "away": a_team})))
    return legs


class Matches:
    """The matches on ``index``."""

    def __init__(self, index: Index, replayed: Replayed, sides: Sides) -> None:
        self.index = index
        self.replayed = replayed
        self.sides = sides

    def add(
        self,
        db: Connection,
        *,
        task: str,
        task_version: str,
        params: Mapping[str, Any],
        a: TeamRef,
        b: TeamRef,
        step_deadline: float,
        submitter: str,
        legs: Sequence[tuple[int, Team]],
        trial_ids: Sequence[int],
    ) -> int:
        """Insert a match whose legs (seed and who plays home, in order) were just
        queued as ``trial_ids`` in the transaction ``db``; its id."""
        if len(legs) != len(trial_ids):
            raise ArchiveError(f"{len(legs)} legs for {len(trial_ids)} trials")
        result = db.execute(
            sa.insert(matches).values(
                task=task,
                task_version=task_version,
                params=dict(params),
                a_repository=a.repository,
                a_ref=a.ref,
                a_commit=a.commit,
                b_repository=b.repository,
                b_ref=b.ref,
                b_commit=b.commit,
                step_deadline=step_deadline,
                submitter=submitter,
                created=self.index.clock(),
                cancel_requested=False,
            )
        )
        key = result.inserted_primary_key
        assert key is not None
        match_id = int(key[0])
        db.execute(
            sa.insert(match_legs),
            [
                {"match_id": match_id, "leg": n, "seed": seed, "home": home, "trial_id": trial}
                for n, ((seed, home), trial) in enumerate(zip(legs, trial_ids, strict=True))
            ],
        )
        return match_id

    def get(self, match_id: int) -> Match:
        """One match (RecordNotFound)."""
        with self.index.engine.connect() as db:
            row = db.execute(sa.select(matches).where(M.id == match_id)).one_or_none()
            if row is None:
                raise RecordNotFound("match", str(match_id))
            return self._build(db, [row])[0]

    def find(
        self, filters: MatchFilters, *, limit: int = 50, before: int | None = None
    ) -> MatchPage:
        """Matches matching ``filters``, newest first, a page at a time."""
        query = sa.select(matches).where(*_conditions(filters))
        if before is not None:
            query = query.where(M.id < before)
        query = query.order_by(M.id.desc()).limit(limit + 1)
        with self.index.engine.connect() as db:
            rows = db.execute(query).all()
            more = len(rows) > limit
            items = self._build(db, rows[:limit])
        return MatchPage(items, items[-1].id if more and items else None)

    def under_way(self, *, limit: int = 10) -> list[Match]:
        """The matches queued or being played, newest first (at most ``limit``)."""
        query = (
            sa.select(matches)
            .where(M.signature.is_(None), M.finished.is_(None))
            .order_by(M.id.desc())
            .limit(4 * limit)
        )
        with self.index.engine.connect() as db:
            found = self._build(db, db.execute(query).all())
        return [m for m in found if not m.status.ended][:limit]

    def of_task(self, task: str) -> list[Match]:
        """Every match of ``task``, oldest first."""
        with self.index.engine.connect() as db:
            rows = db.execute(sa.select(matches).where(M.task == task).order_by(M.id)).all()
            return self._build(db, rows)

    def ladder(self, task: str) -> list[LadderRow]:
        """The task's ladder: every commit that played a finished, verified match of it."""
        return ladder_of(self.of_task(task))

    def add_entry(
        self, db: Connection, *, task: str, team: TeamRef, public: bool, submitter: str
    ) -> int:
        """Enter ``team`` (its commit pinned) on ``task``'s ladder in the transaction
        ``db``; its entry's id (the one it has, if that commit was entered before)."""
        e = ladder_entries.c
        found = db.execute(
            sa.select(e.id).where(
                e.task == task, e.repository == team.repository, e.commit == team.commit
            )
        ).scalar()
        if found is not None:
            return int(found)
        result = db.execute(
            sa.insert(ladder_entries).values(
                task=task,
                repository=team.repository,
                ref=team.ref,
                commit=team.commit,
                public=public,
                submitter=submitter,
                created=self.index.clock(),
            )
        )
        key = result.inserted_primary_key
        assert key is not None
        return int(key[0])

    def entries(self, task: str) -> list[LadderEntry]:
        """The commits entered on ``task``'s ladder, first entered first."""
        e = ladder_entries.c
        with self.index.engine.connect() as db:
            rows = db.execute(sa.select(ladder_entries).where(e.task == task).order_by(e.id)).all()
        return [
            LadderEntry(
                id=r.id,
                task=r.task,
                team=TeamRef(repository=r.repository, ref=r.ref, commit=r.commit),
                public=r.public,
                submitter=r.submitter,
                created=moment(r.created),
            )
            for r in rows
        ]

    def joined_since(self, db: Connection, submitter: str, since: float) -> int:
        """How many commits ``submitter`` entered on ladders since ``since``."""
        e = ladder_entries.c
        return int(
            db.execute(
                sa.select(sa.func.count())
                .select_from(ladder_entries)
                .where(e.submitter == submitter, e.created >= since)
            ).scalar_one()
        )

    def of_trial(self, trial_id: int) -> int | None:
        """The match the trial is a leg of, if any."""
        with self.index.engine.connect() as db:
            return db.execute(
                sa.select(match_legs.c.match_id).where(match_legs.c.trial_id == trial_id)
            ).scalar()

    def trials(self, match_id: int) -> list[int]:
        """The trials of a match's legs, in order."""
        with self.index.engine.connect() as db:
            return list(
                db.execute(
                    sa.select(match_legs.c.trial_id)
                    .where(match_legs.c.match_id == match_id)
                    .order_by(match_legs.c.leg)
                ).scalars()
            )

    def request_cancel(self, match_id: int) -> None:
        with self.index.begin() as db:
            db.execute(sa.update(matches).where(M.id == match_id).values(cancel_requested=True))

    def sign(self, match_id: int, signature: Mapping[str, Any], finished: float) -> bool:
        """Keep the lab's signature of a match whose legs have all ended; False if it
        was signed already (the first signature stays)."""
        with self.index.begin() as db:
            return (
                db.execute(
                    sa.update(matches)
                    .where(M.id == match_id, M.signature.is_(None))
                    .values(signature=dict(signature), finished=finished)
                ).rowcount
                == 1
            )

    def _build(self, db: Connection, rows: Sequence[Any]) -> list[Match]:
        """The matches of ``rows``, with their legs (two queries for all)."""
        ids = [r.id for r in rows]
        if not ids:
            return []
        t, leg = trials.c, match_legs.c
        found = db.execute(
            sa.select(
                leg.match_id,
                leg.leg,
                leg.seed,
                leg.home,
                t.id,
                t.status,
                t.outcome,
                t.reason,
                t.metrics,
                t.data_digest,
                t.finished,
            )
            .join(trials, t.id == leg.trial_id)
            .where(leg.match_id.in_(ids))
            .order_by(leg.match_id, leg.leg)
        ).all()
        verdicts = self._verdicts(db, [f.id for f in found])
        by_match: dict[int, list[tuple[LegRow, float | None]]] = {i: [] for i in ids}
        sides: dict[str, Sequence[str]] = {}
        tasks = {r.id: r.task for r in rows}
        for f in found:
            task = tasks[f.match_id]
            if task not in sides:
                sides[task] = self.sides(task)
            row = LegRow.of(
                leg=f.leg,
                trial=f.id,
                seed=f.seed,
                home=f.home,
                status=Status(f.status),
                outcome=Outcome(f.outcome) if f.outcome else None,
                metrics=f.metrics,
                sides=sides[task],
                verified=verdicts.get(f.id),
                data_digest=f.data_digest,
                said=f.reason,
            )
            by_match[f.match_id].append((row, f.finished))
        return [_match(r, by_match[r.id]) for r in rows]

    def _verdicts(self, db: Connection, trial_ids: Iterable[int]) -> dict[int, bool | None]:
        ids = list(trial_ids)
        if not ids:
            return {}
        found = db.execute(
            sa.select(derived.c.trial_id, derived.c.digest).where(
                derived.c.trial_id.in_(ids), derived.c.name == REPLAY
            )
        ).all()
        return {r.trial_id: self.replayed(r.digest) for r in found}


def _match(row: Any, found: list[tuple[LegRow, float | None]]) -> Match:
    legs = [leg for leg, _ in found]
    status = status_of(legs, row.cancel_requested)
    ended = [f for _, f in found if f is not None]
    finished = row.finished
    if finished is None and ended and status.ended:
        finished = max(ended)
    return Match(
        id=row.id,
        task=row.task,
        task_version=row.task_version,
        params=dict(row.params),
        a=TeamRef(repository=row.a_repository, ref=row.a_ref, commit=row.a_commit),
        b=TeamRef(repository=row.b_repository, ref=row.b_ref, commit=row.b_commit),
        step_deadline=row.step_deadline,
        submitter=row.submitter,
        status=status,
        created=moment(row.created),
        finished=moment(finished) if finished is not None else None,
        legs=legs,
        score=score_of(legs),
        verified=verified_of(legs),
        signature=row.signature,
    )


def _conditions(f: MatchFilters) -> list[sa.ColumnElement[bool]]:
    conditions: list[sa.ColumnElement[bool]] = []
    if f.task is not None:
        conditions.append(M.task == f.task)
    if f.repository is not None:
        names = spellings(f.repository)
        conditions.append(sa.or_(M.a_repository.in_(names), M.b_repository.in_(names)))
    if f.commit is not None:  # a whole commit, or its first digits (an index range)
        commit = f.commit.lower()
        if len(commit) == 40:
            conditions.append(sa.or_(M.a_commit == commit, M.b_commit == commit))
        else:
            end = commit + "g"
            conditions.append(
                sa.or_(
                    sa.and_(M.a_commit >= commit, M.a_commit < end),
                    sa.and_(M.b_commit >= commit, M.b_commit < end),
                )
            )
    if f.submitter is not None:
        conditions.append(M.submitter == f.submitter)
    return conditions
