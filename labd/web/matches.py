"""The matches' pages: one match as it is played, the latest matches, a task's ladder.

    GET /matches/{id}    the two teams, the score (legs won by A, by B, drawn) and what it
                         adds up to, whether every counted leg's replay verified and the
                         match is signed, whether it counts on the ladder; a row per leg
                         (seed, who played home, goals, who won and how, its replay's
                         verdict, its trial) and each leg's video where the lab has
                         rendered it. While it is queued or running, ``static/match.js``
                         follows it through the API and updates the page in place
    GET /matches         the latest matches (``?task=``), a page at a time
    GET /ladders/{task}  the task's ladder (``repository.ladder``): each commit's rating
                         with its 95 % interval, its matches and legs won, lost, drawn;
                         a task that teams do not play has none (404)

The words a page says of a match are made here (``MatchSaid``, ``LegSaid``);
``static/match-words.js`` says the same of the API's JSON, so a page that updated itself
reads as it would reloaded.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Annotated

from fastapi import APIRouter, Query, Request
from fastapi.responses import HTMLResponse

from labd.api.common import Lab
from labd.api.errors import ApiError
from labd.api.models import Id
from labd.sim import registry
from labd.web.evaluations import DASH, POLL_MS, plural
from labd.web.problems import PageRoute
from labd.web.render import page
from labd.web.session import Viewer
from repository.index import Derived
from repository.ladder import CENTRE
from repository.match import PROVISIONAL, LadderRow, LegRow, Match, Team, entry
from repository.match_index import MatchFilters
from repository.trial import Status
from repository.well_known import VIDEO

router = APIRouter(include_in_schema=False, route_class=PageRoute)
PAGE = 50  # matches a list shows at a time
RECENT = 10  # a ladder's task's latest matches, under it
DIVERGED_LISTED = 10  # legs named in "diverged (legs ...)"
HOW = {"goal": "on goals", "time": "at time", "forfeit": "by forfeit"}  # ended_by, in words


def played() -> list[str]:
    """The tasks two teams play: those with a ladder."""
    return [n for n in registry.names() if len(registry.get(n).sides) == 2]


def short(repository: str) -> str:
    """A repository as a list names it: its last two path segments ("…/owner/name"),
    the whole in the cell's title."""
    segments = repository.rstrip("/").removesuffix(".git").split("/")
    tail = "/".join(segments[-2:])
    return tail if len(segments) <= 2 else f"…/{tail}"


def team(side: Team) -> str:
    return side.upper()


def score_words(m: Match) -> str:
    """What the score adds up to: who won the match once it has ended (by legs won), how
    far it is before, and that a cancelled one counts for no one."""
    n = len(m.legs)
    ended = sum(leg.status.ended for leg in m.legs)
    if m.status is Status.CANCELLED:
        return f"cancelled after {ended} of {plural(n, 'leg')}: it counts for no one"
    if not m.status.ended:
        return f"{ended} of {plural(n, 'leg')} ended so far"
    counted = sum(leg.counts for leg in m.legs)
    if not counted:
        return "no leg had a result"
    s = m.score
    lead = "A won the match" if s.a > s.b else "B won the match" if s.b > s.a else "a tie"
    words = f"{lead}, {s.a}{DASH}{s.b} with {plural(s.draws, 'draw')}"
    if counted < n:
        words += f"; {n - counted} of {plural(n, 'leg')} without a result"
    return words


def replay_words(legs: Sequence[LegRow], verified: bool) -> str:
    """Whether every counted leg's replay came back identical, or what is missing."""
    counted = [leg for leg in legs if leg.counts]
    c = len(counted)
    if verified:
        return f"✓ verified: all {plural(c, 'counted leg')} replayed identically"
    if not c:
        return "not verified: no leg has a result yet"
    same = sum(leg.verified is True for leg in counted)
    diverged = [leg.leg for leg in counted if leg.verified is False]
    missing = c - same - len(diverged)
    parts = [f"{same} of {plural(c, 'counted leg')} replayed identically"]
    if diverged:
        listed = ", ".join(str(n) for n in diverged[:DIVERGED_LISTED])
        more = ", ..." if len(diverged) > DIVERGED_LISTED else ""
        which = "leg" if len(diverged) == 1 else "legs"
        parts.append(f"{len(diverged)} diverged ({which} {listed}{more})")
    if missing:
        parts.append(f"{missing} not replayed yet")
    return "not verified: " + "; ".join(parts)


def signed_words(m: Match) -> str:
    if m.signature:
        return f"signed by the lab (key {m.signature.get('key', '?')})"
    if m.status.ended:
        return "not signed: this lab has no signing key"
    return "signed by the lab when every leg has ended"


def ladder_words(m: Match) -> str:
    """Whether the match counts on its task's ladder (``repository.match.ladder_legs``)."""
    if entry(m.a) == entry(m.b):
        return "not on the ladder: a commit against itself says nothing of its rating"
    if m.status is Status.CANCELLED:
        return "not on the ladder: a cancelled match counts for no one"
    if not m.status.ended:
        return "on the ladder once every leg has ended and every counted leg verified"
    if not m.verified:
        return "not on the ladder until every counted leg's replay has verified"
    return "counts on the ladder"


def leg_state(leg: LegRow) -> str:
    """A leg's badge: its outcome once finished, else its status."""
    return leg.outcome.value if leg.outcome is not None else leg.status.value


def result_words(leg: LegRow) -> str:
    """Who won the leg and how: "A won on goals", "draw at time", "B won by forfeit
    (A forfeited)"; "-" without a result."""
    if leg.result is None:
        return "-"
    who = "draw" if leg.result == "draw" else f"{team(leg.result)} won"
    words = f"{who} {HOW[leg.reason]}" if leg.reason else who
    if leg.forfeited:
        words += f" ({', '.join(team(t) for t in leg.forfeited)} forfeited)"
    return words


def goals_words(leg: LegRow) -> str:
    if leg.goals is None:
        return "-"
    return f"{leg.goals.get('a', 0)}{DASH}{leg.goals.get('b', 0)}"


def verdict_words(leg: LegRow) -> str:
    """A leg's replay: verified, diverged, not yet (of a leg with a result), else "-"."""
    if leg.verified is True:
        return "✓ verified"
    if leg.verified is False:
        return "diverged"
    return "not yet" if leg.counts else "-"


@dataclass(frozen=True)
class LegSaid:
    """A leg's row as the page shows it (``static/match-words.js`` the same)."""

    leg: LegRow
    state: str
    goals: str
    result: str
    verdict: str
    video: bool  # the lab has rendered its video (else its trial's page renders it)

    @classmethod
    def of(cls, leg: LegRow, video: Derived | None) -> LegSaid:
        return cls(
            leg=leg,
            state=leg_state(leg),
            goals=goals_words(leg),
            result=result_words(leg),
            verdict=verdict_words(leg),
            video=video is not None,
        )


@dataclass(frozen=True)
class MatchSaid:
    """What a page says of a match (``static/match-words.js`` the same)."""

    score: str
    verified: bool
    replays: str
    signed: str
    ladder: str

    @classmethod
    def of(cls, m: Match) -> MatchSaid:
        return cls(
            score=score_words(m),
            verified=m.verified,
            replays=replay_words(m.legs, m.verified),
            signed=signed_words(m),
            ladder=ladder_words(m),
        )


@router.get("/matches/{match_id}", response_class=HTMLResponse)
def match(request: Request, match_id: Id, service: Lab, viewer: Viewer) -> HTMLResponse:
    m = service.matches.get(match_id)
    legs = [LegSaid.of(leg, service.index.derived(leg.trial).get(VIDEO)) for leg in m.legs]
    return page(
        request,
        "match.html",
        {"m": m, "said": MatchSaid.of(m), "legs": legs, "poll_ms": POLL_MS, "short": short},
        user=viewer,
    )


@router.get("/matches", response_class=HTMLResponse)
def matches(
    request: Request,
    service: Lab,
    viewer: Viewer,
    task: Annotated[str | None, Query(max_length=64, description="a task")] = None,
    before: Annotated[Id | None, Query(description="the next page's cursor")] = None,
) -> HTMLResponse:
    found = service.matches.find(MatchFilters(task=task or None), limit=PAGE, before=before)
    return page(
        request,
        "matches.html",
        {
            "matches": [(m, score_words(m)) for m in found.items],
            "task": task or "",
            "tasks": played(),
            "next_cursor": found.next,
            "short": short,
        },
        user=viewer,
    )


@dataclass(frozen=True)
class Rung:
    """A row of a ladder as its page shows it, with its interval drawn on a common scale
    (``low``, ``high``, ``mark``: per cent of the scale's width)."""

    rank: int
    row: LadderRow
    rating: str
    interval: str
    record: str
    low: float
    high: float
    mark: float


def rungs(rows: Sequence[LadderRow]) -> tuple[list[Rung], tuple[int, int]]:
    """The ladder's rows in words, and the scale their intervals are drawn on: from the
    lowest end to the highest, widened to hold ``CENTRE`` and rounded out to 50 points."""
    if not rows:
        return [], (int(CENTRE), int(CENTRE))
    lo = min(CENTRE, *(r.interval[0] for r in rows))
    hi = max(CENTRE, *(r.interval[1] for r in rows))
    lo, hi = 50 * ((lo - 1) // 50), 50 * (-((-hi - 1) // 50))
    width = hi - lo

    def at(x: float) -> float:
        return round(100 * (x - lo) / width, 2)

    made = [
        Rung(
            rank=n,
            row=r,
            rating=f"{r.rating:.0f}",
            interval=f"{r.interval[0]:.0f}{DASH}{r.interval[1]:.0f}",
            record=f"{r.wins}{DASH}{r.losses}{DASH}{r.draws}",
            low=at(r.interval[0]),
            high=at(r.interval[1]),
            mark=at(r.rating),
        )
        for n, r in enumerate(rows, 1)
    ]
    return made, (int(lo), int(hi))


@router.get("/ladders/{task}", response_class=HTMLResponse)
def ladder(request: Request, task: str, service: Lab, viewer: Viewer) -> HTMLResponse:
    spec = registry.get(task)
    if len(spec.sides) != 2:
        raise ApiError(
            404,
            f"{spec.name} is not played by two teams, so it has no ladder;"
            f" the tasks that have one: {', '.join(played()) or 'none'}",
            title="No ladder",
        )
    made, scale = rungs(service.matches.ladder(spec.name))
    latest = service.matches.find(MatchFilters(task=spec.name), limit=RECENT).items
    return page(
        request,
        "ladder.html",
        {
            "spec": spec,
            "rungs": made,
            "scale": scale,
            "centre": int(CENTRE),
            "provisional": PROVISIONAL,
            "matches": [(m, score_words(m)) for m in latest],
            "short": short,
        },
        user=viewer,
    )
