"""Matches: two commits queued to play a task teams play, each seed twice, then signed.

Submitting a match checks and resolves both repositories once, as a trial's
submission does (``Submissions.prepare``), then queues its legs, all or none, in the
transaction that writes the match (``Queue.submit_many``): every seed twice, A at home
then B at home (``repository.match_index.leg_orders``), each leg counting towards the
submitter's daily limit. A leg is public when both repositories are.

When a leg ends its match is looked at (``settle``): once the last has ended the lab
signs the match's statement (``repository.match.statement``). Cancelling a match
cancels its legs still queued and stops those running; a cancelled match counts for no
one on the ladder, and a leg is never cancelled alone (``LegOfMatch``).
"""

from __future__ import annotations

import logging

from pydantic import BaseModel, ConfigDict, Field
from sqlalchemy.engine import Connection

from repository.index import User
from repository.match import MAX_SEEDS, Match, statement
from repository.match_index import Matches, leg_orders
from repository.signing import Keyring
from repository.trial import TeamRef, Value
from scheduler.errors import InvalidRequest, NotYours
from scheduler.queue import Queue
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
    params: dict[str, Value] = Field(default_factory=dict, description="task parameters")


class Matchmaker:
    """Submits, cancels and signs matches."""

    def __init__(self, submissions: Submissions, matches: Matches, keyring: Keyring | None) -> None:
        self.submissions = submissions
        self.queue: Queue = submissions.queue
        self.host = submissions.host
        self.matches = matches
        self.keyring = keyring
        self.queue.on_ended.append(self.settle)

    def submit(self, user: User, request: MatchRequest) -> int:
        """Check, resolve both teams and queue every leg; the new match's id.

        Raises InvalidRequest, RepositoryError or QuotaExceeded, having written nothing.
        """
        task = request.task
        sides = self.host.sides(task)  # an unknown task is refused before fetching
        if len(sides) != 2:
            raise InvalidRequest(
                f"{task} is not played by two teams: a match is of a task with two sides"
                " (soccer-1v1, soccer-2v2)"
            )
        self.host.check(task, request.params)
        a = self.submissions.prepare(request.a.repository, request.a.ref, task, request.params)
        b = self.submissions.prepare(request.b.repository, request.b.ref, task, request.params)
        for team, prepared in (("A", a), ("B", b)):
            if prepared.order.data:
                raise InvalidRequest(
                    f"team {team}'s lab.toml has [data]: a match's teams learn from no records"
                )
        b_team = TeamRef(repository=b.order.repository, ref=b.order.ref, commit=b.order.commit)
        a_order = a.order.model_copy(update={"public": a.order.public and b.order.public})
        legs = leg_orders(a_order, b_team, range(request.seeds))
        task_version = self.host.task_version(task)

        def add(db: Connection, ids: list[int]) -> int:
            return self.matches.add(
                db,
                task=task,
                task_version=task_version,
                params=a_order.params,
                a=TeamRef(repository=a_order.repository, ref=a_order.ref, commit=a_order.commit),
                b=b_team,
                submitter=user.name,
                legs=[(seed, home) for seed, home, _ in legs],
                trial_ids=ids,
            )

        match_id = self.queue.submit_many(user, [order for _, _, order in legs], then=add)
        log.info(
            "match %d queued for %s: %s against %s, %d legs", match_id, user.name, a, b, len(legs)
        )
        return match_id

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
