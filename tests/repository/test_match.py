"""A match told from its own view (``repository.match``): each leg's result from the
sides' metrics, the score, and which matches the ladder counts."""

from __future__ import annotations

import datetime as dt
from typing import Any

from repository.match import (
    LegRow,
    Match,
    ladder_legs,
    ladder_of,
    opponents,
    score_of,
    verified_of,
)
from repository.trial import Outcome, Status, TeamRef

SIDES = ("home", "away")
A = TeamRef(repository="https://example.org/mover.git", commit="a" * 40)
B = TeamRef(repository="https://example.org/still.git", commit="b" * 40)


def leg(n: int, home: str, metrics: dict[str, Any] | None, **more: Any) -> LegRow:
    return LegRow.of(
        leg=n,
        trial=100 + n,
        seed=n // 2,
        home=home,  # type: ignore[arg-type]
        status=more.pop("status", Status.FINISHED),
        outcome=more.pop("outcome", Outcome.SUCCESS),
        metrics=metrics,
        sides=SIDES,
        verified=more.pop("verified", True),
    )


def won(side: str, by: str = "goal", **goals: int) -> dict[str, Any]:
    forfeited = "" if by != "forfeit" else ("away" if side == "home" else "home")
    return {
        "winner": side,
        "ended_by": by,
        "forfeited": forfeited,
        "home_goals": goals.get("home", 0),
        "away_goals": goals.get("away", 0),
    }


def match(legs: list[LegRow], *, status: Status = Status.FINISHED, b: TeamRef = B) -> Match:
    return Match(
        id=1,
        task="soccer-1v1",
        task_version="1",
        params={},
        a=A,
        b=b,
        step_deadline=10.0,
        submitter="alice",
        status=status,
        created=dt.datetime.now(dt.UTC),
        finished=None,
        legs=legs,
        score=score_of(legs),
        verified=verified_of(legs),
    )


def test_a_leg_is_told_from_the_match_s_view_whoever_played_home():
    at_home = leg(0, "a", won("home", home=1))
    assert (at_home.result, at_home.goals, at_home.reason) == ("a", {"a": 1, "b": 0}, "goal")
    away = leg(1, "b", won("away", away=2, home=1))  # B at home lost: A won away
    assert (away.result, away.goals) == ("a", {"b": 1, "a": 2})
    forfeit = leg(2, "b", won("away", "forfeit"))
    assert (forfeit.result, forfeit.reason, forfeit.forfeited) == ("a", "forfeit", ["b"])
    drawn = leg(3, "a", {"winner": "draw", "ended_by": "time", "forfeited": ""})
    assert (drawn.result, drawn.goals) == ("draw", {"a": 0, "b": 0})
    unplayed = leg(4, "a", None, outcome=Outcome.ERROR)
    assert unplayed.result is None and not unplayed.counts
    assert score_of([at_home, away, forfeit, drawn, unplayed]).model_dump() == {
        "a": 3, "b": 0, "draws": 1
    }  # fmt: skip


def test_a_match_is_verified_when_every_counted_leg_replayed_the_same():
    legs = [leg(0, "a", won("home")), leg(1, "b", won("away"))]
    assert verified_of(legs)
    assert not verified_of([*legs[:1], leg(1, "b", won("away"), verified=None)])
    assert not verified_of([*legs[:1], leg(1, "b", won("away"), verified=False)])
    assert verified_of([*legs, leg(2, "a", None, outcome=Outcome.ERROR, verified=None)])
    assert not verified_of([leg(0, "a", None, outcome=Outcome.ERROR)])  # nothing counted


def test_the_ladder_counts_finished_verified_matches_only():
    legs = [leg(0, "a", won("home")), leg(1, "b", won("away", "forfeit"))]
    assert len(ladder_legs([match(legs)])) == 2
    cancelled = match(legs, status=Status.CANCELLED)
    running = match(legs, status=Status.RUNNING)
    unverified = match([legs[0], leg(1, "b", won("away"), verified=False)])
    itself = match(legs, b=A)
    assert ladder_legs([cancelled, running, unverified, itself]) == []
    rows = ladder_of([match(legs)] * 3)
    assert [r.repository for r in rows] == [A.repository, B.repository]
    top, bottom = rows
    assert (top.wins, top.losses, bottom.losses, top.matches) == (6, 0, 6, 1)
    assert top.interval[0] <= top.rating and bottom.rating <= bottom.interval[1]
    assert top.rating > bottom.rating


def test_a_joining_commit_plays_the_least_played_and_the_nearest_in_turn():
    others = ["old", "busy", "strong", "weak", "fresh"]
    played = {"old": 9, "busy": 12, "strong": 6, "weak": 6, "fresh": 0}
    ratings = {"old": 1000.0, "busy": 1040.0, "strong": 1400.0, "weak": 700.0}
    chosen = opponents("me", others, ratings, played)
    assert chosen == ["fresh", "old", "strong"]  # fewest; nearest 1000; then fewest again
    rated = opponents("me", others, {**ratings, "me": 1390.0}, played)
    assert rated == ["fresh", "strong", "weak"]
    assert opponents("me", ["me", "old"], ratings, played) == ["old"]  # never itself
    assert opponents("me", [], ratings, played) == []
    assert opponents("me", others, ratings, played, count=5) == [
        "fresh", "old", "strong", "busy", "weak"
    ]  # fmt: skip
