"""The benchmarks' pages: a benchmark with its leaderboard, and one run of it.

    GET /benchmarks/{name}      its tasks (each on a suite, normalized how), its
                                leaderboard (``repository.benchmark_run.leaderboard``:
                                each commit's first run, ranked by IQM once finished and
                                verified) with each IQM's 95 % interval as a bar, and the
                                performance profiles of its top runs; an unknown name is
                                the API's 404, naming the known ones
    GET /benchmark-runs/{id}    the run: IQM, mean and median with their intervals, a row
                                per task (its evaluation, episodes ended, normalized mean),
                                its performance profile, its signature. While it is queued
                                or running, ``static/benchmark-run.js`` asks the API for it
                                and reloads the page when it has moved

A task's page links the benchmarks it is a task of (``of_task``, the templates'
``benchmarks_of``).

Every plot is an SVG drawn here (no inline style: the pages' Content-Security-Policy
forbids it; ``static/benchmarks.css`` colours them by class). Scores are normalized to
[0, 1], so every bar and profile shares that one scale.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from fastapi import APIRouter, Request
from fastapi.responses import HTMLResponse

from labd.api.benchmarks import board, known
from labd.api.common import Lab
from labd.api.models import Id
from labd.sim import registry
from labd.web.evaluations import DASH, POLL_MS, plural, rounded
from labd.web.matches import short
from labd.web.problems import PageRoute
from labd.web.render import page, templates
from labd.web.session import Viewer
from repository.benchmark_run import BenchmarkLeaderRow, BenchmarkRun

router = APIRouter(include_in_schema=False, route_class=PageRoute)
PROFILED = 5  # the top runs whose performance profiles a benchmark's page draws
PLACES = 3  # decimals of a normalized score

# The profile plot's frame, in the SVG's own units.
WIDTH, HEIGHT = 640, 300
LEFT, RIGHT, TOP, BOTTOM = 52, 16, 12, 40
TICKS = (0.0, 0.25, 0.5, 0.75, 1.0)

HOW = (
    "The IQM is the interquartile mean of every ended episode's normalized score, pooled"
    " over the tasks (the mean of the middle half), as rliable defines it; its 95 %"
    " interval, and the mean's and median's, are a stratified bootstrap over each task's"
    " episodes, seeded by the run, so the same run always shows the same interval."
)


def score(value: float | None) -> str:
    return "-" if value is None else rounded(value, PLACES)


def spread(interval: tuple[float, float] | None) -> str:
    """A 95 % interval's ends joined by an en dash ("" for none)."""
    if interval is None:
        return ""
    return f"{rounded(interval[0], PLACES)}{DASH}{rounded(interval[1], PLACES)}"


def at(value: float) -> float:
    """A normalized score as per cent of a bar's width."""
    return round(100 * min(max(value, 0.0), 1.0), 2)


@dataclass(frozen=True)
class Standing:
    """A leaderboard row as the page shows it, its IQM's interval drawn on [0, 1]."""

    row: BenchmarkLeaderRow
    iqm: str
    interval: str
    mean: str
    low: float
    high: float
    mark: float | None


def standing(row: BenchmarkLeaderRow) -> Standing:
    low, high = row.iqm_interval or (0.0, 0.0)
    return Standing(
        row=row,
        iqm=score(row.iqm),
        interval=spread(row.iqm_interval),
        mean=score(row.mean),
        low=at(low),
        high=at(high),
        mark=None if row.iqm is None else at(row.iqm),
    )


@dataclass(frozen=True)
class Curve:
    """A run's performance profile as a step curve (an SVG path), its legend's words."""

    series: int  # its colour (``static/benchmarks.css``: .series-0 …)
    run: int
    label: str
    path: str


def x_of(tau: float) -> float:
    return round(LEFT + tau * (WIDTH - LEFT - RIGHT), 2)


def y_of(fraction: float) -> float:
    return round(TOP + (1 - fraction) * (HEIGHT - TOP - BOTTOM), 2)


def step_path(points: Sequence[tuple[float, float]]) -> str:
    """The profile (τ, fraction above τ) as a step: each fraction held until the next τ."""
    if not points:
        return ""
    (tau, fraction), rest = points[0], points[1:]
    parts = [f"M{x_of(tau)} {y_of(fraction)}"]
    for tau, fraction in rest:
        parts.append(f"H{x_of(tau)} V{y_of(fraction)}")
    return " ".join(parts)


def curves(runs: Sequence[BenchmarkRun]) -> list[Curve]:
    """The runs' profiles, those that have one, in the order given."""
    return [
        Curve(
            series=n,
            run=r.id,
            label=f"#{r.id} {short(r.repository)}@{r.commit[:10]} (IQM {score(r.iqm)})",
            path=step_path(r.profile),
        )
        for n, r in enumerate(x for x in runs if x.profile)
    ]


def frame() -> dict[str, object]:
    """The plot's axes and ticks, for the template."""
    return {
        "width": WIDTH,
        "height": HEIGHT,
        "left": LEFT,
        "right": WIDTH - RIGHT,
        "top": TOP,
        "bottom": HEIGHT - BOTTOM,
        "ticks": [(rounded(t, 2), x_of(t), y_of(t)) for t in TICKS],
    }


def of_task(task: str) -> list[str]:
    """The benchmarks that ``task`` is a task of, by name."""
    return [b.name for b in registry.benchmarks() if any(t.task == task for t in b.tasks)]


templates.env.globals["benchmarks_of"] = of_task  # for templates/task.html


@router.get("/benchmarks/{name}", response_class=HTMLResponse)
def benchmark(request: Request, name: str, service: Lab, viewer: Viewer) -> HTMLResponse:
    found = known(name)
    rows = board(service, name)
    top = [service.benchmark_runs.get(r.run) for r in rows[:PROFILED]]
    return page(
        request,
        "benchmark.html",
        {
            "b": found,
            "board": [standing(r) for r in rows],
            "curves": curves(top),
            "frame": frame(),
            "how": HOW,
            "short": short,
            "plural": plural,
        },
        user=viewer,
    )


@dataclass(frozen=True)
class TaskLine:
    """A task of a run as its page shows it."""

    task: str
    suite: str
    evaluation: int
    status: str
    done: str
    mean: str
    interval: str
    verified: bool


def signed_words(run: BenchmarkRun) -> str:
    if run.signature:
        return f"signed by the lab (key {run.signature.get('key', '?')})"
    if run.status.ended:
        return "not signed: this lab has no signing key"
    return "signed by the lab when its last episode has ended"


def verified_words(run: BenchmarkRun) -> str:
    if run.verified:
        return f"✓ verified: every task's evaluation replayed all {plural(run.episodes, 'episode')}"
    waiting = sum(not t.verified for t in run.evaluations)
    return f"not verified: {plural(waiting, 'task')} of {len(run.evaluations)} not all replayed"


@router.get("/benchmark-runs/{run_id}", response_class=HTMLResponse)
def benchmark_run(request: Request, run_id: Id, service: Lab, viewer: Viewer) -> HTMLResponse:
    run = service.benchmark_runs.get(run_id)
    tasks = [
        TaskLine(
            task=t.task,
            suite=t.suite,
            evaluation=t.evaluation,
            status=t.status.value,
            done=f"{t.done} of {t.episodes}",
            mean=score(t.normalized_mean),
            interval=spread(t.normalized_interval),
            verified=t.verified,
        )
        for t in run.evaluations
    ]
    numbers = [
        ("IQM", score(run.iqm), spread(run.iqm_interval)),
        ("mean", score(run.mean), spread(run.mean_interval)),
        ("median", score(run.median), spread(run.median_interval)),
    ]
    return page(
        request,
        "benchmark_run.html",
        {
            "run": run,
            "numbers": numbers,
            "tasks": tasks,
            "curves": curves([run]),
            "frame": frame(),
            "how": HOW,
            "verified": verified_words(run),
            "signed": signed_words(run),
            "poll_ms": POLL_MS,
            "plural": plural,
        },
        user=viewer,
    )
