"""Matches: two commits queued to play a task teams play, each seed twice, then signed.

Submitting a match checks and resolves both repositories once, as a trial's
submission does (``Submissions.prepare``), then queues its legs, all or none, in the
transaction that writes the match (``Queue.submit_many``): every seed twice, A at home
then B at home (``repository.match_index.leg_orders``), each leg counting towards the
submitter's daily limit. A leg is public when both repositories are.

A commit entered on a task's ladder (``join``) is given its matches at once, against
commits entered before it: in turn those with the fewest matches (so no entry starves)
and those rated nearest it, up to ``repository.match.OPPONENTS``, each counting towards
the joiner's daily limit, within a budget of entries a day (``LadderBudget``). The first
entry waits for the next to come.

When a leg ends its match is looked at (``settle``): once the last has ended the lab
signs the match's statement (``repository.match.statement``). Cancelling a match
cancels its legs still queued and stops those running; a cancelled match counts for no
one on the ladder, and a leg is never cancelled alone (``LegOfMatch``).
"""

from __future__ import annotations

import logging
from collections import Counter
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

from pydantic import BaseModel, ConfigDict, Field
from sqlalchemy.engine import Connection

from repository.index import User
from repository.match import (
    MAX_SEEDS,
    MAX_STEP_DEADLINE,
    STEP_DEADLINE,
    Match,
    Team,
    entry,
    ladder_of,
    opponents,
    statement,
)
from repository.match_index import Matches, leg_orders
from repository.signing import Keyring
from repository.trial import Order, Status, TeamRef, Value
from scheduler.errors import InvalidRequest, NotYours, OverLadderBudget
from scheduler.queue import DAY, Queue
from scheduler.submit import Submissions

log = logging.getLogger("scheduler.matches")


class TeamRequest(BaseModel):
    """One team of a match: a repository at a ref."""

    model_config = ConfigDict(extra="forbid")

    repository: str = Field(min_length=1, max_length=2048, description="a git URL or path")
    ref: str | None = Field(None, max_length=256, description="branch, tag or commit")


class MatchRequest(BaseModel):
    """What to play: a task teams play, its parameters, the number of seeds (each
    played twice, the sides swapped), and the two teams."""

    model_config = ConfigDict(extra="forbid")

    task: str = Field(min_length=1, max_length=64, description="a task teams play (soccer-1v1)")
    a: TeamRequest
    b: TeamRequest
    seeds: int = Field(2, ge=1, le=MAX_SEEDS, description="seeds 0 to N-1, two legs each")
    step_deadline: float = Field(
        STEP_DEADLINE,
        ge=1,
        le=MAX_STEP_DEADLINE,
        description="seconds a team may keep the other waiting for its step before it forfeits",
    )
    params: dict[str, Value] = Field(default_factory=dict, description="task parameters")


@dataclass(frozen=True)
class LadderBudget:
    """How many commits a user may enter on ladders in 24 hours; each entry's matches
    count towards their daily limit of trials too."""

    per_day: int = 5


@dataclass(frozen=True)
class Joined:
    """A commit entered on a ladder: its entry, and the matches scheduled for it."""

    entry: int
    matches: list[int]


@dataclass(frozen=True)
class _Planned:
    """A match ready to queue: its teams resolved, its legs' orders."""

    a: Order
    b: TeamRef
    step_deadline: float
    legs: list[tuple[int, Team, Order]]


class Matchmaker:
    """Submits, cancels and signs matches, and schedules a ladder's."""

    def __init__(
        self,
        submissions: Submissions,
        matches: Matches,
        keyring: Keyring | None,
        budget: LadderBudget | None = None,
    ) -> None:
        self.submissions = submissions
        self.queue: Queue = submissions.queue
        self.host = submissions.host
        self.matches = matches
        self.keyring = keyring
        self.budget = budget or LadderBudget()
        self.queue.on_ended.append(self.settle)

    def _task(self, task: str, params: Mapping[str, Value]) -> None:
        """``InvalidRequest`` unless ``task`` is played by two teams and takes ``params``."""
        if len(self.host.sides(task)) != 2:  # an unknown task is refused too
            raise InvalidRequest(
                f"{task} is not played by two teams: a match is of a task with two sides"
                " (soccer-1v1, soccer-2v2)"
            )
        self.host.check(task, params)

    def _team(self, name: str, team: TeamRequest, task: str, params: Mapping[str, Value]) -> Order:
        """The team's code resolved and checked, as a trial of ``task`` would be."""
        order = self.submissions.prepare(team.repository, team.ref, task, params).order
        if order.data:
            raise InvalidRequest(
                f"team {name}'s lab.toml has [data]: a match's teams learn from no records"
            )
        return order

    def _plan(self, a: Order, b: Order, seeds: int, step_deadline: float) -> _Planned:
        b_team = TeamRef(repository=b.repository, ref=b.ref, commit=b.commit)
        a = a.model_copy(update={"public": a.public and b.public})
        return _Planned(
            a, b_team, step_deadline, leg_orders(a, b_team, range(seeds), step_deadline)
        )

    def _queue(
        self, user: User, task: str, planned: Sequence[_Planned], then: Callable[[Connection], None]
    ) -> list[int]:
        """Queue every planned match whole, all or none; their ids."""
        task_version = self.host.task_version(task)

        def add(db: Connection, ids: list[int]) -> list[int]:
            then(db)
            made, start = [], 0
            for plan in planned:
                legs = ids[start : start + len(plan.legs)]
                start += len(plan.legs)
                a = plan.a
                made.append(
                    self.matches.add(
                        db,
                        task=task,
                        task_version=task_version,
                        params=a.params,
                        a=TeamRef(repository=a.repository, ref=a.ref, commit=a.commit),
                        b=plan.b,
                        step_deadline=plan.step_deadline,
                        submitter=user.name,
                        legs=[(seed, home) for seed, home, _ in plan.legs],
                        trial_ids=legs,
                    )
                )
            return made

        orders = [order for plan in planned for _, _, order in plan.legs]
        return self.queue.submit_many(user, orders, then=add)

    def submit(self, user: User, request: MatchRequest) -> int:
        """Check, resolve both teams and queue every leg; the new match's id.

        Raises InvalidRequest, RepositoryError or QuotaExceeded, having written nothing.
        """
        self._task(request.task, request.params)
        a = self._team("A", request.a, request.task, request.params)
        b = self._team("B", request.b, request.task, request.params)
        [match_id] = self._queue(
            user,
            request.task,
            [self._plan(a, b, request.seeds, request.step_deadline)],
            then=lambda _db: None,
        )
        log.info(
            "match %d queued for %s: %s@%s against %s@%s",
            match_id,
            user.name,
            a.repository,
            a.commit[:12],
            b.repository,
            b.commit[:12],
        )
        return match_id

    def join(self, user: User, task: str, team: TeamRequest, *, seeds: int = 1) -> Joined:
        """Enter a commit on ``task``'s ladder and queue its matches: against up to
        ``OPPONENTS`` entered commits, those with the fewest matches and those rated
        nearest it in turn (``repository.match.opponents``), each ``seeds`` seeds. Within
        the user's ladder budget (``OverLadderBudget``) and daily limit (``QuotaExceeded``);
        all or nothing."""
        self._task(task, {})
        order = self._team("joining", team, task, {})
        joining = entry(TeamRef(repository=order.repository, commit=order.commit))
        entered = {e.name: e for e in self.matches.entries(task)}
        every = self.matches.of_task(task)
        ratings = {f"{r.repository}@{r.commit}": r.rating for r in ladder_of(every)}
        played = Counter(  # queued and under way too: the next joiner plays the others
            entry(team) for m in every if m.status is not Status.CANCELLED for team in (m.a, m.b)
        )
        chosen = opponents(joining, list(entered), ratings, played)
        planned = []
        for name in chosen:
            other = entered[name].team
            rival = self._team(
                name, TeamRequest(repository=other.repository, ref=other.commit), task, {}
            )
            planned.append(self._plan(order, rival, seeds, STEP_DEADLINE))
        entry_id: list[int] = []

        def enter(db: Connection) -> None:
            since = self.queue.clock() - DAY
            used = self.matches.joined_since(db, user.name, since)
            if used >= self.budget.per_day:
                raise OverLadderBudget(user.name, used, self.budget.per_day)
            entry_id.append(
                self.matches.add_entry(
                    db,
                    task=task,
                    team=TeamRef(repository=order.repository, ref=order.ref, commit=order.commit),
                    public=order.public,
                    submitter=user.name,
                )
            )

        if planned:
            made = self._queue(user, task, planned, then=enter)
        else:  # the first on the ladder: its matches come as others join
            with self.queue.index.begin() as db:
                enter(db)
            made = []
        log.info(
            "%s entered %s on the %s ladder: %d matches queued against %s",
            user.name,
            joining,
            task,
            len(made),
            ", ".join(chosen) or "no one yet",
        )
        return Joined(entry_id[0], made)

    def cancel(self, user: User, match_id: int) -> Match:
        """Cancel the legs still queued and stop those running (``NotYours`` unless
        ``user`` submitted it); the match after."""
        match = self.matches.get(match_id)
        if match.submitter != user.name:
            raise NotYours(match_id, match.submitter, "cancel", what="match")
        self.matches.request_cancel(match_id)
        for trial_id in self.matches.trials(match_id):
            self.queue.cancel(trial_id, user, whole=True)
        self.settle_match(match_id)  # if nothing was left to end
        return self.matches.get(match_id)

    def settle(self, trial_id: int) -> None:
        """After a trial ended: sign its match if that was the last leg."""
        match_id = self.matches.of_trial(trial_id)
        if match_id is not None:
            self.settle_match(match_id)

    def settle_match(self, match_id: int) -> None:
        match = self.matches.get(match_id)
        if not match.status.ended or match.signature is not None:
            return
        finished = self.queue.clock()
        signature = None
        if self.keyring is not None:
            signature = self.keyring.sign(statement(match, finished)).to_json()
        if self.matches.sign(match_id, signature or {}, finished):
            score = match.score
            log.info(
                "match %d %s: A %d, B %d, %d drawn",
                match_id,
                match.status,
                score.a,
                score.b,
                score.draws,
            )
