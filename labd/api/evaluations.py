"""The HTTP API of evaluations: submit one, follow it, compare two, rank a suite's.

An evaluation is one commit on every episode of one suite of a task
(``repository.evaluation``); its episodes are trials like any other. Reading is public;
submitting, cancelling and rerunning need a token or a signed-in session. A held-out
suite's episodes stay the operator's until the suite version is retired: the API shows
such an evaluation's aggregate once it has ended, never an episode's seed, outcome, time
or record (their trials answer 403, their blobs 404).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

from fastapi import APIRouter, Depends, Query, Request
from fastapi.responses import JSONResponse
from pydantic import BaseModel
from starlette.concurrency import run_in_threadpool

from labd.api.common import Lab, Writer
from labd.api.errors import ApiError, responses
from labd.api.models import EvaluationPage, EvaluationView, Id, TaskView, task_view
from labd.api.state import App
from labd.sim import registry
from repository.evaluation import (
    Comparison,
    Evaluation,
    EvaluationRequest,
    LeaderRow,
    compare,
    leaderboard,
)
from repository.evaluation_index import EvaluationFilters

router = APIRouter(tags=["evaluations"])


class Leaderboard(BaseModel):
    """A suite's leaderboard: each commit's first evaluation of it, verified ones ranked
    best first, then the rest unranked (``repository.evaluation.leaderboard``)."""

    task: str
    suite: str
    suite_version: int
    rows: list[LeaderRow]


@dataclass(frozen=True)
class EvaluationQuery:
    """The filters of GET /api/evaluations."""

    task: str | None = None
    suite: str | None = None
    repository: str | None = None
    commit: Annotated[
        str | None,
        Query(pattern=r"^[0-9a-fA-F]{4,40}$", description="a commit or its first 4+ digits"),
    ] = None
    submitter: Annotated[str | None, Query(description="who submitted it")] = None
    limit: Annotated[int, Query(ge=1, le=200)] = 50
    before: Annotated[Id | None, Query(description="the `next` of the page before")] = None


def view(evaluation: Evaluation, base: str) -> EvaluationView:
    return EvaluationView(
        **dict(evaluation),
        url=f"{base}/api/evaluations/{evaluation.id}",
        page=f"{base}/evaluations/{evaluation.id}",
    )


def _base(request: Request) -> str:
    return str(request.base_url).rstrip("/")


def _created(service: Lab, evaluation_id: int, request: Request) -> JSONResponse:
    body = view(service.evaluations.get(evaluation_id), _base(request))
    return JSONResponse(
        body.model_dump(mode="json"), status_code=201, headers={"Location": body.url}
    )


@router.post(
    "/api/evaluations",
    status_code=201,
    response_model=EvaluationView,
    responses=responses(400, 401, 403, 404, 413, 422, 429, 503),
)
async def submit(
    body: EvaluationRequest, request: Request, service: Lab, app: App, user: Writer
) -> JSONResponse:
    """Resolve the ref to a commit now, and queue a trial of it on every episode of the
    suite (each counts towards the daily limit)."""
    evaluation_id = await service.submissions.in_pool(service.evaluator.submit, user, body)
    app.on_submit()
    return await run_in_threadpool(_created, service, evaluation_id, request)


@router.get("/api/evaluations", responses=responses(422))
def list_evaluations(
    request: Request, service: Lab, q: Annotated[EvaluationQuery, Depends()]
) -> EvaluationPage:
    """Evaluations, newest first, a page at a time."""
    filters = EvaluationFilters(
        task=q.task, suite=q.suite, repository=q.repository, commit=q.commit, submitter=q.submitter
    )
    page = service.evaluations.find(filters, limit=q.limit, before=q.before)
    base = _base(request)
    return EvaluationPage(evaluations=[view(e, base) for e in page.items], next=page.next)


@router.get("/api/evaluations/compare", responses=responses(404, 422))
def compare_evaluations(
    service: Lab,
    a: Annotated[Id, Query(description="evaluation A")],
    b: Annotated[Id, Query(description="evaluation B")],
) -> Comparison:
    """Two evaluations of one suite version, paired by episode: how often only one
    succeeded, McNemar's exact p-value, and the paired reward difference (of a held-out
    suite's, once both have ended: counts, never which episodes)."""
    return paired(service, a, b)


def paired(service: Lab, a: int, b: int) -> Comparison:
    """Evaluations ``a`` and ``b`` compared (``ApiError`` 422 if they do not pair).

    Held-out evaluations are compared on their whole rows, which the comparison turns
    into counts alone; but only once both have ended, since counts that move as
    episodes end would time them."""
    shown = [service.evaluations.get(a), service.evaluations.get(b)]
    try:
        compared = compare(shown[0], shown[1])  # of one suite version, or a ValueError
    except ValueError as err:
        raise ApiError(422, str(err)) from None
    if not any(e.hidden for e in shown):
        return compared
    if not all(e.status.ended for e in shown):
        raise ApiError(
            422, "a held-out evaluation is compared once it has ended: its episodes are not shown"
        )
    whole = [service.evaluations.get(e.id, reveal=True) if e.hidden else e for e in shown]
    return compare(whole[0], whole[1])


@router.get("/api/evaluations/{evaluation_id}", responses=responses(404, 422))
def show(evaluation_id: Id, request: Request, service: Lab) -> EvaluationView:
    """One evaluation: its episodes, its score with intervals, whether it verified."""
    return view(service.evaluations.get(evaluation_id), _base(request))


@router.post("/api/evaluations/{evaluation_id}/cancel", responses=responses(401, 403, 404, 422))
def cancel(evaluation_id: Id, request: Request, service: Lab, user: Writer) -> EvaluationView:
    """Cancel the episodes still queued and stop those running; the finished ones are
    kept, and the score is marked partial (and left off the leaderboard)."""
    return view(service.evaluator.cancel(user, evaluation_id), _base(request))


@router.post(
    "/api/evaluations/{evaluation_id}/rerun",
    status_code=201,
    response_model=EvaluationView,
    responses=responses(401, 403, 404, 422, 429),
)
def rerun(
    evaluation_id: Id, request: Request, service: Lab, app: App, user: Writer
) -> JSONResponse:
    """Rerun every episode (the same commit, seeds and pinned data) as a new evaluation,
    whose ``reproduced`` says how many episodes came out identical."""
    new_id = service.evaluator.rerun(user, evaluation_id)
    app.on_submit()
    return _created(service, new_id, request)


@router.get("/api/tasks/{name}", tags=["tasks"], responses=responses(404))
def task(name: str, service: Lab) -> TaskView:
    """One task: its parameters and its episode suites."""
    return task_view(name, service.evaluations.retired(registry.get(name).name))


@router.get("/api/tasks/{name}/leaderboard", tags=["tasks"], responses=responses(404, 422))
def task_leaderboard(
    name: str,
    service: Lab,
    suite: Annotated[str, Query(max_length=32, description="a suite of the task")] = "dev",
) -> Leaderboard:
    """The suite's leaderboard, as this lab runs it now: each commit's first evaluation
    of the current suite version (never its best; none if its submitter cancelled it),
    ranked by success rate then mean reward once the lab's replays verified every
    episode, each with its intervals; single trials are not on it."""
    spec = registry.get(name)
    current = spec.suite(suite)
    if current is None:
        known = ", ".join(s.name for s in spec.suites) or "none"
        raise ApiError(404, f"task {name} has no suite {suite!r}; its suites: {known}")
    found = service.evaluations.of_suite(name, current.name, current.version)
    return Leaderboard(
        task=name, suite=current.name, suite_version=current.version, rows=leaderboard(found)
    )
