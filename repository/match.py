"""Matches: two commits, A and B, play a task teams play, and what that adds up to.

A match is (task, parameters, seeds, commit A, commit B), both commits pinned when it
is submitted. Each seed is played twice with the sides swapped: A at home, then B at
home. Each leg is a trial of kind ``match`` whose own code plays home and whose
``away_*`` team plays away (``repository.trial.Order.away``); its result is in its
filed metrics, as the leg runner wrote them from the sides' view
(``scheduler.outcome.judge_leg``: ``winner``, ``ended_by``, ``forfeited`` and each
side's ``SIDE_goals``). Here that result is told from the match's view, A and B
(``LegRow``), and a match's score is the legs' (``Match``). A leg counts once it has
finished with a result: one that could not be played, or that ended with every side
failing, counts for no one.

The ladder of a task (``repository.ladder``) rates commits from the legs of every
finished match of it whose every leg with a result was verified by its replay.
"""

from __future__ import annotations

import datetime as dt
import itertools
from collections.abc import Mapping, Sequence
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from repository.ladder import CENTRE, Leg, Rating, ladder
from repository.trial import Outcome, Status, TeamRef

Team = Literal["a", "b"]
Result = Literal["a", "b", "draw"]
Reason = Literal["goal", "time", "forfeit"]
MAX_SEEDS = 50  # seeds a match may play (two legs each)
STEP_DEADLINE = 10.0  # seconds a team may take to step once the other has, by default
MAX_STEP_DEADLINE = 60.0  # the longest a match may give (its legs hold a worker meanwhile)
MATCH = "labd.match/1"  # the schema of a match's signed statement


def other(team: Team) -> Team:
    return "b" if team == "a" else "a"


class LegRow(BaseModel):
    """One leg of a match, told from the match's view."""

    model_config = ConfigDict(frozen=True)

    leg: int = Field(description="its place in the match, from 0")
    trial: int
    seed: int
    home: Team = Field(description="who played home: a or b")
    status: Status
    outcome: Outcome | None
    goals: dict[str, int] | None = Field(
        default=None, description="each team's goals, {a, b}; None until it has a result"
    )
    result: Result | None = Field(default=None, description="who won: a, b or draw")
    reason: Reason | None = Field(default=None, description="how it ended: goal, time or forfeit")
    forfeited: list[Team] = Field(default_factory=list)
    verified: bool | None = Field(
        default=None, description="its replay verified; None: not (yet) replayed"
    )
    data_digest: str | None = None
    said: str = Field(default="", description="the leg's reason, in words")

    @classmethod
    def of(
        cls,
        *,
        leg: int,
        trial: int,
        seed: int,
        home: Team,
        status: Status,
        outcome: Outcome | None,
        metrics: Mapping[str, Any] | None,
        sides: Sequence[str],
        verified: bool | None,
        data_digest: str | None = None,
        said: str = "",
    ) -> LegRow:
        """The leg of trial ``trial`` from its filed ``metrics`` (the sides' view, with
        ``sides`` the task's, home first)."""
        base = cls(
            leg=leg,
            trial=trial,
            seed=seed,
            home=home,
            status=status,
            outcome=outcome,
            verified=verified,
            data_digest=data_digest,
            said=said,
        )
        found = metrics or {}
        if outcome is not Outcome.SUCCESS or len(sides) < 2 or not found.get("winner"):
            return base
        team_of = {sides[0]: home, sides[1]: other(home)}
        goals = {team_of[side]: int(found.get(f"{side}_goals", 0)) for side in sides[:2]}
        winner = str(found["winner"])
        result: Result = "draw" if winner == "draw" else team_of[winner]
        ended_by = str(found.get("ended_by", ""))
        forfeits = [team_of[s] for s in str(found.get("forfeited", "")).split(",") if s in team_of]
        return base.model_copy(
            update={
                "goals": goals,
                "result": result,
                "reason": ended_by if ended_by in ("goal", "time", "forfeit") else None,
                "forfeited": forfeits,
            }
        )

    @property
    def counts(self) -> bool:
        """It has a result to count."""
        return self.result is not None

    def stated(self) -> dict[str, Any]:
        """What a signed statement says of the leg."""
        return {
            "leg": self.leg,
            "trial": self.trial,
            "seed": self.seed,
            "home": self.home,
            "result": self.result,
            "reason": self.reason,
            "goals": self.goals,
            "data_digest": self.data_digest,
        }


class Score(BaseModel):
    """The legs each team won, and those drawn."""

    model_config = ConfigDict(frozen=True)

    a: int
    b: int
    draws: int


class Match(BaseModel):
    """A match, its legs and its score (``GET /api/matches/{id}``)."""

    model_config = ConfigDict(frozen=True)

    id: int
    task: str
    task_version: str
    params: dict[str, Any]
    a: TeamRef
    b: TeamRef
    step_deadline: float = Field(description="seconds a team may keep the other waiting")
    submitter: str
    status: Status
    created: dt.datetime
    finished: dt.datetime | None
    legs: list[LegRow]
    score: Score
    verified: bool = Field(
        description="every leg with a result was verified by its replay (and there is one)"
    )
    signature: dict[str, Any] | None = None

    @property
    def seeds(self) -> list[int]:
        return sorted({leg.seed for leg in self.legs})


def score_of(legs: Sequence[LegRow]) -> Score:
    counted = [leg for leg in legs if leg.counts]
    return Score(
        a=sum(leg.result == "a" for leg in counted),
        b=sum(leg.result == "b" for leg in counted),
        draws=sum(leg.result == "draw" for leg in counted),
    )


def verified_of(legs: Sequence[LegRow]) -> bool:
    counted = [leg for leg in legs if leg.counts]
    return bool(counted) and all(leg.verified is True for leg in counted)


def status_of(legs: Sequence[LegRow], cancel_requested: bool) -> Status:
    """A match's status from its legs' (as an evaluation's from its episodes')."""
    if legs and all(leg.status is Status.QUEUED for leg in legs) and not cancel_requested:
        return Status.QUEUED
    if any(not leg.status.ended for leg in legs):
        return Status.RUNNING
    if any(leg.status is Status.CANCELLED for leg in legs):
        return Status.CANCELLED
    return Status.FINISHED


def entry(team: TeamRef) -> str:
    """How the ladder names a commit: ``REPOSITORY@COMMIT``."""
    return f"{team.repository}@{team.commit}"


def ladder_legs(matches: Sequence[Match]) -> list[Leg]:
    """The legs the ladder rates: every counted leg of every finished, verified match
    (a match cancelled, or with a leg not verified, counts for no one: cancelling a
    losing match buys nothing, nor does a record the lab could not reproduce)."""
    legs = []
    for match in matches:
        if match.status is not Status.FINISHED or not match.verified:
            continue
        a, b = entry(match.a), entry(match.b)
        if a == b:
            continue  # a commit against itself says nothing of its rating
        for leg in match.legs:
            if leg.result is not None:
                points = {"a": 1.0, "b": 0.0, "draw": 0.5}[leg.result]
                legs.append(Leg(str(match.id), a, b, points))
    return legs


PROVISIONAL = 3  # matches under which a rating is provisional: one lucky match says little
OPPONENTS = 3  # matches a commit joining a ladder is given


class LadderRow(BaseModel):
    """One commit on a task's ladder (``GET /api/ladders/{task}``)."""

    model_config = ConfigDict(frozen=True)

    repository: str
    commit: str
    rating: float
    interval: tuple[float, float]
    matches: int
    wins: int
    losses: int
    draws: int
    provisional: bool = Field(
        default=False, description=f"fewer than {PROVISIONAL} matches: a rating to take lightly"
    )

    @classmethod
    def of(cls, rating: Rating) -> LadderRow:
        repository, _, commit = rating.entry.rpartition("@")
        return cls(
            repository=repository,
            commit=commit,
            rating=round(rating.rating, 1),
            interval=(round(rating.interval[0], 1), round(rating.interval[1], 1)),
            matches=rating.matches,
            wins=rating.wins,
            losses=rating.losses,
            draws=rating.draws,
            provisional=rating.matches < PROVISIONAL,
        )


def ladder_of(matches: Sequence[Match], *, seed: int = 0) -> list[LadderRow]:
    """A task's ladder from its matches: Bradley-Terry ratings with bootstrap intervals
    (``repository.ladder``), best first."""
    return [LadderRow.of(r) for r in ladder(ladder_legs(matches), seed=seed)]


class LadderEntry(BaseModel):
    """A commit entered on a task's ladder, and who entered it."""

    model_config = ConfigDict(frozen=True)

    id: int
    task: str
    team: TeamRef
    public: bool
    submitter: str
    created: dt.datetime

    @property
    def name(self) -> str:
        return entry(self.team)


def opponents(
    joining: str,
    others: Sequence[str],
    ratings: Mapping[str, float],
    played: Mapping[str, int],
    *,
    count: int = OPPONENTS,
) -> list[str]:
    """Whom a commit joining a ladder plays: first those with the fewest matches (so no
    entry starves), then those rated nearest to it (an unrated commit counts as the
    prior's 1000), each once; ties go to the earlier entry in ``others``."""
    pool = [o for o in dict.fromkeys(others) if o != joining]
    order = {name: n for n, name in enumerate(pool)}
    few = sorted(pool, key=lambda o: (played.get(o, 0), order[o]))
    mine = ratings.get(joining, CENTRE)
    near = sorted(pool, key=lambda o: (abs(ratings.get(o, CENTRE) - mine), order[o]))
    chosen: list[str] = []
    turns = itertools.cycle((few, near))  # one of the fewest matches, one of the nearest...
    while len(chosen) < min(count, len(pool)):
        chosen.append(next(o for o in next(turns) if o not in chosen))
    return chosen


def statement(match: Match, finished: float) -> dict[str, Any]:
    """What the lab vouches for when every leg of a match has ended: who played what,
    each leg's result and data digest (its replay's verdict comes later, beside the
    record), and the score."""
    return {
        "schema": MATCH,
        "match": match.id,
        "status": match.status.value,
        "finished": dt.datetime.fromtimestamp(finished, dt.UTC).isoformat(),
        "task": match.task,
        "task_version": match.task_version,
        "params": match.params,
        "a": match.a.model_dump(),
        "b": match.b.model_dump(),
        "step_deadline": match.step_deadline,
        "legs": [leg.stated() for leg in match.legs],
        "score": match.score.model_dump(),
    }
