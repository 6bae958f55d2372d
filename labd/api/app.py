"""The lab's HTTP API (FastAPI; OpenAPI at ``/openapi.json``, docs at ``/docs``).

Reading the archive is public. Writing (submitting, rerunning, cancelling) needs a
token, sent as ``Authorization: Bearer TOKEN``; ``labd users add NAME`` prints one.

    GET  /api/tasks                        the tasks and their parameters
    POST /api/trials                       submit: repository, ref, task, params, seed
    GET  /api/trials                       filters: repository commit task status user
                                           since until; limit, before (the page cursor)
    GET  /api/trials/{id}                  one trial, with its manifest
    GET  /api/trials/{id}/data.mcap        its record, checked against its digest
    GET  /api/trials/{id}/logs/{stream}    the controller's stdout or stderr
    POST /api/trials/{id}/rerun            a new trial from the same manifest
    POST /api/trials/{id}/cancel           cancel a queued or running trial
    GET  /api/commits/{sha}                a commit's trials and their reruns

Errors are ``{"error": "what went wrong and what to do"}`` with a 4xx status.
"""

from __future__ import annotations

import datetime as dt
from collections.abc import Callable
from dataclasses import dataclass
from typing import Annotated, Any

from fastapi import APIRouter, Depends, FastAPI, Query, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, StreamingResponse
from pydantic import BaseModel, ConfigDict, Field

from labd import __version__
from labd.api import views, workers
from labd.api.common import ApiError, Lab, Writer, blob_response
from labd.service import Service
from labd.sim import registry
from repository.errors import ArchiveError, RecordNotFound
from repository.index import STATUSES, Filters
from scheduler.errors import (
    InvalidRequest,
    QueueError,
    QuotaExceeded,
    RepositoryError,
    TooLarge,
)

Value = bool | int | float | str


class SubmitRequest(BaseModel):
    """A trial to run: a repository at a ref, a task, its parameters and a seed."""

    model_config = ConfigDict(extra="forbid")
    repository: str = Field(min_length=1, max_length=2048, description="a git URL or path")
    ref: str | None = Field(None, max_length=256, description="branch, tag or commit")
    task: str = Field(description="a task from /api/tasks")
    params: dict[str, Value] = Field(default_factory=dict)
    seed: int = Field(0, ge=0, le=2**63 - 1)


def create_app(service: Service, *, on_submit: Callable[[], None] | None = None) -> FastAPI:
    """The API over ``service``; ``on_submit`` is called after a trial is queued."""
    app = FastAPI(
        title="labd",
        version=__version__,
        description="A remote robot lab: submit controllers by git URL, browse the archive.",
    )
    app.state.service = service
    app.state.on_submit = on_submit or service.wake
    app.add_exception_handler(ApiError, _api_error)  # type: ignore[arg-type]
    app.add_exception_handler(RequestValidationError, _invalid)  # type: ignore[arg-type]
    app.include_router(router)
    app.include_router(workers.router)
    return app


router = APIRouter()


async def _api_error(_: Request, err: ApiError) -> JSONResponse:
    return JSONResponse({"error": err.message}, status_code=err.status)


async def _invalid(_: Request, err: RequestValidationError) -> JSONResponse:
    problems = list(err.errors())
    if any(p.get("type") == "json_invalid" for p in problems):
        return JSONResponse({"error": "the request body is not valid JSON"}, status_code=400)
    parts = []
    for p in problems:
        where = ".".join(str(x) for x in p.get("loc", ()) if x != "body")
        parts.append(f"{where}: {p.get('msg', 'invalid')}" if where else p.get("msg", ""))
    return JSONResponse({"error": "; ".join(parts)}, status_code=422)


def _base(request: Request) -> str:
    return str(request.base_url).rstrip("/")


def _one(service: Service, trial_id: int) -> dict[str, Any]:
    try:
        return service.index.trial(trial_id)
    except RecordNotFound as err:
        raise ApiError(404, str(err)) from None


@dataclass(frozen=True)
class TrialQuery:
    """The filters of GET /api/trials."""

    repository: str | None = None
    commit: str | None = None
    task: str | None = None
    status: Annotated[str | None, Query(description=" | ".join(STATUSES))] = None
    user: str | None = None
    since: dt.datetime | None = None
    until: dt.datetime | None = None
    rerun_of: int | None = None
    limit: Annotated[int, Query(ge=1, le=500)] = 50
    before: Annotated[int | None, Query(description="the `next` of the page before")] = None


@router.get("/api/tasks", tags=["tasks"])
def tasks() -> dict[str, Any]:
    """The tasks a trial can run, with their parameters."""
    return {"tasks": [views.task(name) for name in registry.names()]}


@router.post("/api/trials", status_code=201, tags=["trials"])
def submit(body: SubmitRequest, request: Request, service: Lab, user: Writer) -> JSONResponse:
    """Resolve the ref to a commit now, and queue a trial of that commit."""
    try:
        trial_id = service.submissions.submit(
            user,
            repository=body.repository,
            ref=body.ref,
            task=body.task,
            params=body.params,
            seed=body.seed,
        )
    except (InvalidRequest, RepositoryError, QuotaExceeded) as err:
        raise _error(err) from None
    request.app.state.on_submit()
    row = views.trial(service.index.trial(trial_id), base=_base(request))
    return JSONResponse(row, status_code=201, headers={"Location": row["url"]})


@router.get("/api/trials", tags=["trials"])
def list_trials(
    request: Request, service: Lab, q: Annotated[TrialQuery, Depends()]
) -> dict[str, Any]:
    """Trials, newest first, a page at a time."""
    filters = Filters(
        repository=q.repository,
        commit=q.commit,
        task=q.task,
        status=q.status,
        submitter=q.user,
        since=_epoch(q.since),
        until=_epoch(q.until),
        rerun_of=q.rerun_of,
    )
    try:
        page = service.index.find(filters, limit=q.limit, before=q.before)
    except ArchiveError as err:
        raise ApiError(422, str(err)) from None
    link = _base(request)
    return {"trials": [views.trial(r, base=link) for r in page.items], "next": page.next}


@router.get("/api/trials/{trial_id}", tags=["trials"])
def show(trial_id: int, request: Request, service: Lab) -> dict[str, Any]:
    """One trial: what was asked, where it is, what came out, its manifest."""
    return views.trial(_one(service, trial_id), base=_base(request), full=True)


@router.get("/api/trials/{trial_id}/data.mcap", tags=["data"])
def data(trial_id: int, service: Lab) -> StreamingResponse:
    """The trial's MCAP record, checked against its digest before it is sent."""
    row = _one(service, trial_id)
    if not row["mcap"]:
        raise ApiError(404, f"trial {trial_id} has no record ({row['status']})")
    return blob_response(service, row["mcap"], "application/x-mcap", f"trial-{trial_id}.mcap")


@router.get("/api/trials/{trial_id}/logs/{stream}", tags=["data"])
def logs(trial_id: int, stream: str, service: Lab) -> StreamingResponse:
    """The controller's ``stdout`` or ``stderr``."""
    if stream not in ("stdout", "stderr"):
        raise ApiError(404, "logs are stdout or stderr")
    row = _one(service, trial_id)
    if not row[stream]:
        raise ApiError(404, f"trial {trial_id} has no {stream} log")
    return blob_response(service, row[stream], "text/plain; charset=utf-8", None)


@router.post("/api/trials/{trial_id}/rerun", status_code=201, tags=["trials"])
def rerun(trial_id: int, request: Request, service: Lab, user: Writer) -> JSONResponse:
    """Queue a new trial from the same commit, task, parameters and seed."""
    _one(service, trial_id)
    try:
        new_id = service.submissions.rerun(user, trial_id)
    except QuotaExceeded as err:
        raise _error(err) from None
    request.app.state.on_submit()
    row = views.trial(service.index.trial(new_id), base=_base(request))
    return JSONResponse(row, status_code=201, headers={"Location": row["url"]})


@router.post("/api/trials/{trial_id}/cancel", tags=["trials"])
def cancel(trial_id: int, request: Request, service: Lab, user: Writer) -> dict[str, Any]:
    """Cancel a queued trial, or stop a running one (its worker ends it shortly)."""
    _one(service, trial_id)
    try:
        service.queue.cancel(trial_id, user)
    except QueueError as err:
        raise ApiError(403, str(err)) from None
    return views.trial(service.index.trial(trial_id), base=_base(request))


@router.get("/api/commits/{sha}", tags=["archive"])
def commit(sha: str, request: Request, service: Lab) -> dict[str, Any]:
    """A commit's trials (newest first), each with its reruns and their verdicts."""
    try:
        page = service.index.commit_page(sha)
    except RecordNotFound as err:
        raise ApiError(404, str(err)) from None
    except ArchiveError as err:
        raise ApiError(422, str(err)) from None
    link = _base(request)
    return {
        "commit": page["commit"],
        "repositories": page["repositories"],
        "trials": [
            {
                **views.trial(row, base=link),
                "reruns": [views.trial(r, base=link) for r in page["reruns"].get(row["id"], [])],
            }
            for row in page["trials"]
        ],
        "rerun_counts": page["rerun_counts"],
        "truncated": page["truncated"],
    }


def _error(err: Exception) -> ApiError:
    if isinstance(err, QuotaExceeded):
        return ApiError(429, str(err))
    if isinstance(err, TooLarge):
        return ApiError(413, str(err))
    return ApiError(422, str(err))


def _epoch(moment: dt.datetime | None) -> float | None:
    if moment is None:
        return None
    if moment.tzinfo is None:
        moment = moment.replace(tzinfo=dt.UTC)
    return moment.timestamp()
