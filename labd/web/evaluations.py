"""The evaluations' pages: one evaluation as it runs, two compared, a rerun, and the
part of a task's page that ranks its evaluations.

    GET  /evaluations/{id}        what was evaluated; its score in words with its 95 %
                                  intervals; whether every replay verified; a cell per
                                  episode, linked to its trial unless held out. While it
                                  is queued or running, ``static/evaluation.js`` follows
                                  it through the API and updates the page in place
    GET  /compare?a=ID&b=ID       two evaluations of one suite version side by side,
                                  paired by episode (``repository.evaluation.compare``);
                                  with only ``a``, a form to choose ``b`` among the same
                                  suite version's evaluations (with neither, to type both)
    POST /evaluations/{id}/rerun  rerun every episode as a new evaluation; to its page

and, for ``GET /tasks/{name}`` (``labd.web.pages``), ``task_board``: the task's suites
and the leaderboard of one suite's evaluations, with their ties.

The words a page says of a score are made here (``Said``); ``static/evaluation-words.js``
says the same of the API's JSON, rounded the same way (half up, as JavaScript's
``Math.round``), so a page that updated itself reads as it would reloaded.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Annotated, Any

from fastapi import APIRouter, Depends, Query, Request
from fastapi.responses import HTMLResponse, RedirectResponse

from labd.api.common import Lab
from labd.api.errors import ApiError
from labd.api.evaluations import paired
from labd.api.models import Id, task_view
from labd.api.state import App
from labd.web.problems import PageRoute
from labd.web.render import page
from labd.web.session import CsrfChecked, SignedIn, Viewer
from repository.evaluation import (
    EpisodeRow,
    Evaluation,
    LeaderRow,
    Score,
    SuiteInfo,
    leaderboard,
)
from repository.evaluation_index import EvaluationFilters
from repository.index import User
from repository.stats import MIN_BOOTSTRAP
from repository.trial import Status

router = APIRouter(include_in_schema=False, route_class=PageRoute)
POLL_MS = 2000  # how often a page following an evaluation asks the API for it
CHOICES = 50  # the evaluations a compare page offers as B
RECENT = 10  # the evaluations of a suite listed on its task's page
STATES = ("success", "fail", "error", "running", "queued", "cancelled")  # a cell's colours
DIVERGED_LISTED = 10  # episodes named in "diverged (episodes ...)"
DASH = "\u2013"  # between a percentage interval's ends


def rounded(value: float, places: int) -> str:
    """``value`` to ``places`` decimals, half up, as short as it reads (``0.7``, ``12``)."""
    scale = 10**places
    return repr(math.floor(value * scale + 0.5) / scale).removesuffix(".0")


def percent(fraction: float) -> str:
    return f"{math.floor(100 * fraction + 0.5)} %"


def plural(n: int, word: str) -> str:
    return f"{n} {word}" if n == 1 else f"{n} {word}s"


def rate_words(score: Score, ended: bool) -> str:
    """The success rate over the suite's episodes with its interval, once every episode
    has ended: "70 % (48 % to 85 %, 95 % Wilson) of 20 episodes", the interval's ends
    joined by an en dash; before, how far it is (a held-out one: not even that)."""
    if score.success_rate is not None and score.success_interval is not None:
        low, high = score.success_interval
        words = f"{percent(score.success_rate)} ({percent(low)}{DASH}{percent(high)}, 95 % Wilson)"
        return f"{words} of {plural(score.episodes, 'episode')}"
    if score.done is None or score.successes is None:
        return "held out: the score is shown once every episode has ended"
    so_far = "ended" if ended else "ended so far"
    return (
        f"{score.done} of {plural(score.episodes, 'episode')} {so_far}, {score.successes} succeeded"
    )


def reward_words(score: Score) -> str:
    """The mean reward with its 95 % bootstrap interval, or why it has none
    (``repository.stats.mean_interval``): too few episodes, or rewards all alike (the
    score does not say which when enough episodes ended: one may have no reward)."""
    if score.mean_reward is None:
        return "no reward yet"
    words = f"mean reward {rounded(score.mean_reward, 3)}"
    if score.reward_interval is not None:
        low, high = score.reward_interval
        return f"{words} ({rounded(low, 3)} to {rounded(high, 3)}, 95 % bootstrap)"
    if score.done is not None and score.done < MIN_BOOTSTRAP:
        few = plural(score.done, "episode")
        return f"{words} ({few}: too few for a 95 % interval, which takes {MIN_BOOTSTRAP})"
    return (
        f"{words} (no 95 % interval: the rewards are all the same, or fewer than {MIN_BOOTSTRAP})"
    )


def replay_words(rows: Sequence[EpisodeRow], verified: bool, episodes: int) -> str:
    """Whether every episode's replay (the lab's own) came back identical, or what is
    missing (of a held-out evaluation, whose rows are not shown: not which)."""
    n = episodes
    if verified:
        return f"✓ verified: all {plural(n, 'episode')} replayed identically"
    if len(rows) < n:
        return "not verified: not every episode's replay verified (yet)"
    same = sum(r.verified is True for r in rows)
    diverged = [r.episode for r in rows if r.verified is False]
    cancelled = sum(r.status is Status.CANCELLED for r in rows)
    missing = n - same - len(diverged) - cancelled
    parts = [f"{same} of {n} replayed identically"]
    if diverged:
        listed = ", ".join(str(e) for e in diverged[:DIVERGED_LISTED])
        more = ", ..." if len(diverged) > DIVERGED_LISTED else ""
        which = "episode" if len(diverged) == 1 else "episodes"
        parts.append(f"{len(diverged)} diverged ({which} {listed}{more})")
    if cancelled:
        parts.append(f"{cancelled} cancelled")
    if missing:
        parts.append(f"{missing} not replayed yet")
    return "not verified: " + "; ".join(parts)


def elsewhere_words(elsewhere: int | None, episodes: int) -> str:
    """How many episodes verified on another machine of the lab's cluster than the one
    that ran them ("" where no cluster replayed any)."""
    if elsewhere is None:
        return ""
    return f"verified on another machine: {elsewhere} of {episodes}"


def duration(seconds: float | None) -> str:
    if seconds is None:
        return "held out"
    if seconds < 120:
        return f"{rounded(seconds, 1)} s"
    return f"{rounded(seconds / 60, 1)} min"


def state(row: EpisodeRow) -> str:
    """An episode's cell colour: its outcome once finished, else its status."""
    return row.outcome.value if row.outcome is not None else row.status.value


def cell_title(row: EpisodeRow) -> str:
    seed = f", seed {row.seed}" if row.seed is not None else ""
    reward = f", reward {rounded(row.reward, 3)}" if row.reward is not None else ""
    return f"episode {row.episode}{seed}: {state(row)}{reward}"


def signed_words(e: Evaluation) -> str:
    if e.signature:
        return f"signed by the lab (key {e.signature.get('key', '?')})"
    if e.status.ended:
        return "not signed: this lab has no signing key"
    return "signed by the lab when every episode has ended"


def partial_words(e: Evaluation) -> str:
    return (
        f"partial: {e.partial_reason}; not every episode counted, so the leaderboard leaves it out"
    )


@dataclass(frozen=True)
class Cell:
    """An episode in the page's grid: a link to its trial (a held-out evaluation's page
    has no grid until its suite version is retired)."""

    episode: int
    state: str
    title: str
    link: str


@dataclass(frozen=True)
class Said:
    """What a page says of an evaluation's score (``static/evaluation-words.js`` the same)."""

    rate: str
    reward: str
    verified: bool
    replays: str
    elsewhere: str
    compute: str
    counts: dict[str, int]
    signed: str
    partial: str

    @classmethod
    def of(cls, e: Evaluation) -> Said:
        counted = Counter(state(r) for r in e.rows)
        return cls(
            rate=rate_words(e.score, e.status.ended),
            reward=reward_words(e.score),
            verified=e.score.verified,
            replays=replay_words(e.rows, e.score.verified, e.episodes),
            elsewhere=elsewhere_words(e.score.verified_elsewhere, e.episodes),
            compute=duration(e.score.compute_seconds),
            counts={s: counted[s] for s in STATES},
            signed=signed_words(e),
            partial=partial_words(e),
        )


def cells(e: Evaluation) -> list[Cell]:
    """The episodes' cells, each linked to its trial (a hidden evaluation has none)."""
    return [
        Cell(
            episode=r.episode,
            state=state(r),
            title=cell_title(r),
            link=f"/trials/{r.trial}",
        )
        for r in e.rows
    ]


@router.get("/evaluations/{evaluation_id}", response_class=HTMLResponse)
def evaluation(request: Request, evaluation_id: Id, service: Lab, viewer: Viewer) -> HTMLResponse:
    e = service.evaluations.get(evaluation_id)
    return page(
        request,
        "evaluation.html",
        {
            "e": e,
            "said": Said.of(e),
            "cells": cells(e),
            "states": STATES,
            "poll_ms": POLL_MS,
            "held": e.hidden,
        },
        user=viewer,
    )


@router.post("/evaluations/{evaluation_id}/rerun", dependencies=[CsrfChecked])
def rerun(
    evaluation_id: Id,
    service: Lab,
    app: App,
    person: Annotated[User, Depends(SignedIn("/evaluations/{evaluation_id}"))],
) -> RedirectResponse:
    """Rerun every episode, as ``POST /api/evaluations/{id}/rerun`` does; to the rerun."""
    new_id = service.evaluator.rerun(person, evaluation_id)
    app.on_submit()
    return RedirectResponse(f"/evaluations/{new_id}", status_code=303)


@dataclass(frozen=True)
class Listed:
    """An evaluation in a list (B's choices, a suite's latest), its success in words."""

    e: Evaluation
    rate: str


@router.get("/compare", response_class=HTMLResponse)
def comparison(
    request: Request,
    service: Lab,
    viewer: Viewer,
    a: Annotated[Id | None, Query(description="evaluation A")] = None,
    b: Annotated[Id | None, Query(description="evaluation B")] = None,
) -> HTMLResponse:
    """A and B paired by episode; a refusal to pair them (another suite or version) is
    the API's 422 with its words."""
    context: dict[str, Any] = {"a": None, "b": None, "compared": None, "choices": []}
    if a is not None:
        first = service.evaluations.get(a)
        context.update(a=first, said_a=Said.of(first))
        if b is None:
            context["choices"] = _choices(service, first)
        else:
            second = service.evaluations.get(b)
            try:
                compared = paired(service, a, b)
            except ApiError as err:
                raise ApiError(422, str(err), title="These two do not compare") from None
            context.update(b=second, said_b=Said.of(second), compared=compared)
            if compared.reward_difference is not None:
                context["difference"] = rounded(compared.reward_difference, 3)
                context["min_pairs"] = MIN_BOOTSTRAP
            if compared.reward_difference_interval is not None:
                low, high = compared.reward_difference_interval
                context["difference_interval"] = f"{rounded(low, 3)} to {rounded(high, 3)}"
    return page(request, "compare.html", context, user=viewer)


def _choices(service: Lab, first: Evaluation) -> list[Listed]:
    """The evaluations ``first`` pairs with: of its task version and suite version."""
    found = service.evaluations.find(
        EvaluationFilters(task=first.task, suite=first.suite, suite_version=first.suite_version),
        limit=CHOICES,
    ).items
    return [
        Listed(e, rate_words(e.score, e.status.ended))
        for e in found
        if e.id != first.id and e.task_version == first.task_version
    ]


@dataclass(frozen=True)
class Standing:
    """A row of a task's leaderboard as its page shows it."""

    row: LeaderRow
    rate: str
    rate_interval: str
    reward: str
    reward_interval: str


def standing(row: LeaderRow) -> Standing:
    """A leaderboard row in words (an unranked one keeps its numbers, and its note)."""
    low, high = row.success_interval
    reward = "-" if row.mean_reward is None else rounded(row.mean_reward, 3)
    spread = ""
    if row.reward_interval is not None:
        spread = f"{rounded(row.reward_interval[0], 3)} to {rounded(row.reward_interval[1], 3)}"
    return Standing(
        row, percent(row.success_rate), f"{percent(low)}{DASH}{percent(high)}", reward, spread
    )


def suite_seeds(suite: SuiteInfo) -> str:
    """How a task page lists a suite's seeds: held out, a range, or the first few."""
    if suite.seeds is None:
        if suite.retired:
            return "held out until retired; public now, on its evaluations' pages"
        return "held out: its seeds are the lab's secret"
    seeds = suite.seeds
    if seeds == list(range(seeds[0], seeds[0] + len(seeds))):
        return f"public: seeds {seeds[0]} to {seeds[-1]}"
    shown = ", ".join(str(s) for s in seeds[:8])
    return f"public: seeds {shown}{', ...' if len(seeds) > 8 else ''}"


def task_board(service: Lab, name: str, suite: str | None) -> dict[str, Any]:
    """A task page's part about evaluations: its suites, the leaderboard of ``suite``
    (by default ``dev``, else its first) as this lab runs it now, and the suite's
    latest evaluations (running and cancelled ones too). An unknown suite is the API's
    404, with the same words."""
    view = task_view(name, service.evaluations.retired(name))
    suites = view.suites
    names = [s.name for s in suites]
    if suite is None:
        suite = "dev" if "dev" in names or not names else names[0]
    chosen = next((s for s in suites if s.name == suite), None)
    if chosen is None and (names or suite != "dev"):
        known = ", ".join(names) or "none"
        raise ApiError(404, f"task {name} has no suite {suite!r}; its suites: {known}")
    board: list[Standing] = []
    recent: list[Listed] = []
    if chosen is not None:
        found = service.evaluations.of_suite(name, chosen.name, chosen.version)
        board = [standing(r) for r in leaderboard(found)]
        latest = service.evaluations.find(
            EvaluationFilters(task=name, suite=chosen.name), limit=RECENT
        ).items
        recent = [Listed(e, rate_words(e.score, e.status.ended)) for e in latest]
    return {
        "suites": [(s, suite_seeds(s)) for s in suites],
        "suite": chosen,
        "board": board,
        "evaluations": recent,
    }
