"""The HTTP API of benchmarks: what each one is (issue 37).

A benchmark is a named set of tasks, each on one of its suites, whose episodes' scores
are normalized to [0, 1] (``repository.benchmark``); task packs declare them
(``labd.sim.registry``). Reading is public.

    GET /api/benchmarks                      every benchmark: name, doc, tasks
    GET /api/benchmarks/{name}               one, with its leaderboard (404 naming
                                             the known ones)
    POST /api/benchmark-runs                 a commit on every task of one (201)
    GET /api/benchmark-runs[/{id}]           runs, with rliable's statistics
    GET /api/benchmark-runs/compare?a=&b=    the probability of improvement

The list's body is the declarations themselves (``BenchmarkList``), as they round-trip:
``labd tasks`` reads them back without loading this module's web server. One benchmark
is its declaration with its leaderboard (``repository.benchmark_run.leaderboard``).
"""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query, Request
from fastapi.responses import JSONResponse
from pydantic import BaseModel, Field
from starlette.concurrency import run_in_threadpool

from labd.api.common import Lab, Writer
from labd.api.errors import ApiError, responses
from labd.api.models import Id
from labd.api.state import App
from labd.errors import LabError
from labd.sim import registry
from repository.benchmark import Benchmark, BenchmarkList
from repository.benchmark_run import (
    BenchmarkLeaderRow,
    BenchmarkRun,
    Compared,
    compare,
    leaderboard,
)
from scheduler.benchmarks import BenchmarkRunRequest

router = APIRouter(tags=["benchmarks"])


@router.get("/api/benchmarks")
def list_benchmarks() -> BenchmarkList:
    """Every benchmark of the lab's task packs, the lab's own first: its tasks, the suite
    of each, and how an episode's score is normalized to [0, 1]."""
    return BenchmarkList(registry.benchmarks())


class BenchmarkView(Benchmark):
    """A benchmark with its leaderboard."""

    leaderboard: list[BenchmarkLeaderRow] = Field(
        description="each commit's first run on the benchmark's own suites, ranked by IQM"
        " once finished and verified; the rest unranked after"
    )


PAGE = 100  # runs read at a time to make a leaderboard


def known(name: str) -> Benchmark:
    """The benchmark ``name``, or the API's 404 naming the known ones."""
    try:
        return registry.benchmark(name)
    except LabError as err:
        raise ApiError(404, str(err), title="No such benchmark") from None


def board(service: Lab, name: str) -> list[BenchmarkLeaderRow]:
    """The leaderboard of ``name``'s runs on its own suites (a run asked with no suite)."""
    runs: list[BenchmarkRun] = []
    before: int | None = None
    while True:
        found, before = service.benchmark_runs.find(benchmark=name, limit=PAGE, before=before)
        runs.extend(r for r in found if r.suite == "")
        if before is None:
            return leaderboard(runs)


@router.get("/api/benchmarks/{name}", responses=responses(404))
def one_benchmark(name: str, service: Lab) -> BenchmarkView:
    """One benchmark: its tasks, the suite of each, how an episode is scored, and its
    leaderboard (each commit's first run, never its best)."""
    found = known(name)
    return BenchmarkView(**dict(found), leaderboard=board(service, name))


class BenchmarkRunView(BenchmarkRun):
    """A benchmark run, with where to find it."""

    url: str = Field(description="this run in the API")


class BenchmarkRunPage(BaseModel):
    runs: list[BenchmarkRunView]
    next: int | None = Field(description="`before` for the next page; null on the last")


def _view(run: BenchmarkRun, request: Request) -> BenchmarkRunView:
    base = str(request.base_url).rstrip("/")
    return BenchmarkRunView(**dict(run), url=f"{base}/api/benchmark-runs/{run.id}")


@router.post(
    "/api/benchmark-runs",
    status_code=201,
    response_model=BenchmarkRunView,
    responses=responses(400, 401, 403, 404, 413, 422, 429, 503),
)
async def submit_run(
    body: BenchmarkRunRequest, request: Request, service: Lab, app: App, user: Writer
) -> JSONResponse:
    """Resolve the ref to a commit now, and queue one evaluation per task of the
    benchmark (every episode counts towards the daily limit)."""
    run_id = await service.submissions.in_pool(service.benchmarker.submit, user, body)
    app.on_submit()
    made = await run_in_threadpool(service.benchmark_runs.get, run_id)
    body_out = _view(made, request)
    return JSONResponse(
        body_out.model_dump(mode="json"), status_code=201, headers={"Location": body_out.url}
    )


@router.get("/api/benchmark-runs", responses=responses(422))
def list_runs(
    request: Request,
    service: Lab,
    *,
    benchmark: str | None = None,
    commit: Annotated[str | None, Query(pattern=r"^[0-9a-fA-F]{40}$")] = None,
    limit: Annotated[int, Query(ge=1, le=100)] = 20,
    before: Annotated[Id | None, Query()] = None,
) -> BenchmarkRunPage:
    """Benchmark runs, newest first, a page at a time."""
    runs, more = service.benchmark_runs.find(
        benchmark=benchmark, commit=commit, limit=limit, before=before
    )
    return BenchmarkRunPage(runs=[_view(r, request) for r in runs], next=more)


@router.get("/api/benchmark-runs/compare", responses=responses(404, 422))
def compare_runs(
    service: Lab,
    a: Annotated[Id, Query(description="run A")],
    b: Annotated[Id, Query(description="run B")],
) -> Compared:
    """The probability that an episode of A scores above one of B, averaged over the
    benchmark's tasks (ties half), with its stratified bootstrap interval."""
    row_a, evaluations_a = service.benchmark_runs.whole(a)
    _, evaluations_b = service.benchmark_runs.whole(b)
    run_a, run_b = service.benchmark_runs.get(a), service.benchmark_runs.get(b)
    try:
        return compare(
            run_a,
            run_b,
            service.host.benchmark(row_a.benchmark),
            [e for _, e in evaluations_a],
            [e for _, e in evaluations_b],
        )
    except ValueError as err:
        raise ApiError(422, str(err)) from None


@router.get("/api/benchmark-runs/{run_id}", responses=responses(404, 422))
def show_run(run_id: Id, request: Request, service: Lab) -> BenchmarkRunView:
    """One run: each task's evaluation and normalized mean, the IQM, mean and median
    over every episode with their 95 % stratified bootstrap intervals, the performance
    profile, and whether every evaluation verified."""
    return _view(service.benchmark_runs.get(run_id), request)
