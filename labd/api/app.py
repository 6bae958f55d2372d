"""The lab's HTTP API (FastAPI; OpenAPI at ``/openapi.json``, docs at ``/docs``).

Reading the archive is public. Writing (submitting, rerunning, cancelling, booking)
needs a token, sent as ``Authorization: Bearer TOKEN`` (``labd users add NAME`` prints
one; a user makes more on the tokens page), or a signed-in page's session cookie with
its CSRF token (``labd.api.common``).

    GET  /healthz, /readyz                 the process answers; it can work (``labd.health``)
    GET  /metrics                          Prometheus' text format (``labd.metrics``)
    GET  /api/status                       the queue and what each busy worker runs
    GET  /api/tasks                        the tasks and their parameters
    GET  /api/benchmarks[/{name}]          the task packs' benchmarks (``labd.api.benchmarks``)
    POST /api/trials                       submit: repository, ref, task, params, seed
    GET  /api/trials                       filters: repository commit task status outcome
                                           kind user since until; limit, before (cursor)
    GET  /api/trials/{id}                  one trial, with its manifest
    GET  /api/trials/{id}/data.mcap        its record, checked against its digest
    GET  /api/trials/{id}/logs/{stream}    the controller's stdout or stderr
    POST /api/trials/{id}/rerun            a new trial from the same manifest
    POST /api/trials/{id}/cancel           cancel a queued or running trial
    GET  /api/commits/{sha}                a commit's trials and their reruns
    /api/reservations, /api/robots/{robot}/..., /api/auth
                                           booking live robots, their calendars, keys,
                                           and the authorizer (``labd.api.reservations``)
    /api/me, /api/tokens                   my account and tokens (``labd.api.accounts``)
    /git/USER/NAME.git                     the playground's repositories, read-only over
                                           git's smart HTTP (``labd.api.git``)

Every body, success or error, is a model of ``labd.api.models``; errors are
``{"error": "what went wrong and what to do"}``, mapped from exceptions in one table
(``labd.api.errors``).
"""

from __future__ import annotations

import datetime as dt
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Annotated, Literal

from fastapi import APIRouter, Depends, FastAPI, Query, Request
from fastapi.responses import JSONResponse, Response, StreamingResponse
from starlette.concurrency import run_in_threadpool

from labd import __version__, health
from labd.api import (
    accounts,
    benchmarks,
    errors,
    evaluations,
    matches,
    playground,
    records,
    reservations,
    summaries,
    workers,
)
from labd.api.builds import Builds
from labd.api.common import Lab, Writer, blob_response
from labd.api.edges import Edges
from labd.api.errors import ApiError, responses
from labd.api.git import GitHttp
from labd.api.models import (
    CancelView,
    CommitView,
    Health,
    Id,
    Keys,
    LabStatus,
    TaskList,
    TrialDetail,
    TrialPage,
    WorkerHealth,
    WorkerView,
    commit_view,
    task_list,
    trial_detail,
    trial_summary,
)
from labd.api.site import Site
from labd.api.state import App, AppState
from labd.api.throttle import Throttle
from labd.authorizer import ReservationAuthorizer
from labd.metrics import CONTENT_TYPE
from labd.service import Service
from repository.index import Filters
from repository.reservations import Reservation
from repository.trial import Kind, Outcome, Status, TrialRequest


def create_app(
    service: Service,
    site: Site | None = None,
    *,
    on_submit: Callable[[], None] | None = None,
    on_reservation: Callable[[Reservation], None] | None = None,
    robots: Sequence[str] = (),
) -> FastAPI:
    """The API over ``service``; ``site`` is what it knows of the live robots (none by
    default); ``on_submit`` is called after a trial is queued, ``on_reservation`` after
    a slot is extended or released; ``robots`` are the live robots that can be booked.
    The pages and ``/docs`` are added by ``labd.web.create_app``."""
    app = FastAPI(
        title="labd",
        version=__version__,
        description="A remote robot lab: submit controllers by git URL, browse the archive.",
        docs_url=None,  # served offline by labd.web, from the lab's own files (no CDN)
        redoc_url=None,
    )
    app.state.lab = AppState(
        service=service,
        on_submit=on_submit or service.wake,
        robots=tuple(robots),
        site=site or Site(),
        throttle=Throttle(service.index.clock),
        keys=ReservationAuthorizer(service.reservations),
        builds=Builds(service.config.data / "exports"),
        on_reservation=on_reservation or _no_bridge,
    )
    errors.install(app)
    parts = (
        router,
        records.router,
        evaluations.router,
        benchmarks.router,
        matches.router,
        summaries.router,
        workers.router,
        workers.blobs,
        accounts.router,
        reservations.router,
        playground.router,
    )
    for part in parts:
        app.include_router(errors.declare_validation(part))
    app.mount("/git", GitHttp(service.hosted), name="git")  # read-only git over HTTP
    app.add_middleware(Edges)
    return app


def _no_bridge(reservation: Reservation) -> None:
    """No bridge to tell of a changed slot: an API without the lab's bridge."""


router = APIRouter()


def _base(request: Request) -> str:
    return str(request.base_url).rstrip("/")


@dataclass(frozen=True)
class TrialQuery:
    """The filters of GET /api/trials."""

    repository: str | None = None
    commit: Annotated[str | None, Query(description="a commit or its first 4+ digits")] = None
    task: str | None = None
    status: Status | None = None
    outcome: Outcome | None = None
    kind: Kind | None = None
    user: Annotated[str | None, Query(description="the submitter")] = None
    since: dt.datetime | None = None
    until: dt.datetime | None = None
    rerun_of: Id | None = None
    limit: Annotated[int, Query(ge=1, le=500)] = 50
    before: Annotated[Id | None, Query(description="the `next` of the page before")] = None


@router.get("/api/status", tags=["lab"])
def status(service: Lab) -> LabStatus:
    """The lab now: trials waiting, and each busy worker's trial and how long it has run."""
    now = time.time()
    local = {w.config.name: w.current for w in service.workers}
    running = []
    for trial in service.queue.running(public=True):  # held-out episodes: never timed here
        here = local.get(trial.worker or "")
        started = trial.started.timestamp() if trial.started else None
        running.append(
            WorkerView(
                worker=trial.worker or "",
                trial=trial.id,
                task=trial.task,
                started=trial.started,
                running_seconds=None if started is None else round(now - started, 1),
                stage=here.stage if here else None,
                stage_seconds=round(here.stage_seconds, 1) if here else None,
            )
        )
    return LabStatus(
        version=__version__,
        queued=service.queue.queued(public=True),
        running=running,
        local_workers=len(service.workers),
        workers=[
            WorkerHealth(worker=h.worker, state=h.state, detail=h.detail, since=h.since)
            for h in sorted(service.queue.health.values(), key=lambda h: h.worker)
        ],
    )


@router.get("/healthz", tags=["lab"])
def healthz() -> Health:
    """The lab's process answers (for a supervisor: restart it if this fails)."""
    return Health(status="ok")


@router.get("/readyz", tags=["lab"], responses=responses(503))
def readyz(service: Lab) -> Health:
    """The lab can do its work: its index and blob store answer, and a worker can run
    trials (a lab with no workers of its own is ready without one, and says so); 503
    naming each check that failed and what it found (``labd.health``)."""
    checks = health.readiness(service)
    failed = [f"{c.name}: {c.detail}" for c in checks if not c.ok]
    if failed:
        raise ApiError(503, "not ready: " + "; ".join(failed))
    return Health(status="ready", checks={c.name: c.detail for c in checks})


@router.get(
    "/metrics",
    tags=["lab"],
    response_class=Response,
    responses={
        200: {
            "content": {CONTENT_TYPE: {"schema": {"type": "string"}}},
            "description": "the metrics, in Prometheus' text format (docs/metrics.md)",
        }
    },
)
def metrics(service: Lab) -> Response:
    """The lab's metrics for Prometheus: trials, evaluations, the queue, workers, the
    bridge's clients and frames, live drivers, replay verdicts, the blob store's errors.
    Public, for an operator's scraper: counts only, no names."""
    return Response(service.metrics.exposition(), media_type=CONTENT_TYPE)


@router.get("/api/keys", tags=["lab"])
def keys(service: Lab) -> Keys:
    """The public keys the lab signs records and exports with (``labd verify --key``)."""
    return Keys(current=service.keyring.current, keys=service.keyring.public_keys())


@router.get("/api/tasks", tags=["tasks"])
def tasks() -> TaskList:
    """The tasks a trial can run, with their parameters (and the task plugins installed
    but left out, with why)."""
    return task_list()


@router.post(
    "/api/trials",
    status_code=201,
    tags=["trials"],
    response_model=TrialDetail,
    responses=responses(400, 401, 403, 413, 422, 429, 503),
)
async def submit(
    body: TrialRequest, request: Request, service: Lab, app: App, user: Writer
) -> JSONResponse:
    """Resolve the ref to a commit now, and queue a trial of that commit.

    The resolving (git, within the lab's resolve timeout) runs in the submissions' own
    threads, never in those that answer readers; 503 when they have all they take.
    """
    trial_id = await service.submissions.submit_async(user, body)
    app.on_submit()
    return await run_in_threadpool(_created, service, trial_id, request)


@router.get("/api/trials", tags=["trials"], responses=responses(422))
def list_trials(request: Request, service: Lab, q: Annotated[TrialQuery, Depends()]) -> TrialPage:
    """Trials, newest first, a page at a time."""
    filters = Filters(
        repository=q.repository,
        commit=q.commit,
        task=q.task,
        status=q.status,
        outcome=q.outcome,
        kind=q.kind,
        submitter=q.user,
        since=_epoch(q.since),
        until=_epoch(q.until),
        rerun_of=q.rerun_of,
    )
    page = service.index.find(filters, limit=q.limit, before=q.before)
    link = _base(request)
    return TrialPage(trials=[trial_summary(t, link) for t in page.items], next=page.next)


@router.get("/api/trials/{trial_id}", tags=["trials"], responses=responses(403, 404))
def show(trial_id: Id, request: Request, service: Lab) -> TrialDetail:
    """One trial: its outcome, what was asked, what came out, its manifest; while it is
    queued, how many wait before it."""
    trial = trial_detail(service.index.readable(trial_id), _base(request))
    if trial.status is Status.QUEUED:
        trial.queued_ahead = service.queue.queued_before(trial_id)
    return trial


@router.get(
    "/api/trials/{trial_id}/data.mcap",
    tags=["data"],
    response_class=StreamingResponse,
    responses={
        200: {"content": {"application/x-mcap": {}}, "description": "the MCAP file"},
        **responses(403, 404, 500),
    },
)
def data(trial_id: Id, service: Lab) -> StreamingResponse:
    """The trial's MCAP record, checked against its digest before it is sent."""
    trial = service.index.readable(trial_id)
    if not trial.mcap:
        raise ApiError(
            404, f"trial {trial_id} has no record ({_state(trial.status, trial.outcome)})"
        )
    return blob_response(service, trial.mcap, "application/x-mcap", f"trial-{trial_id}.mcap")


@router.get(
    "/api/trials/{trial_id}/logs/{stream}",
    tags=["data"],
    response_class=StreamingResponse,
    responses={
        200: {"content": {"text/plain": {}}, "description": "the log, as the controller wrote it"},
        **responses(403, 404, 422, 500),
    },
)
def logs(trial_id: Id, stream: Literal["stdout", "stderr"], service: Lab) -> StreamingResponse:
    """The controller's ``stdout`` or ``stderr``."""
    trial = service.index.readable(trial_id)
    digest = trial.stdout if stream == "stdout" else trial.stderr
    if not digest:
        raise ApiError(404, f"trial {trial_id} has no {stream} log")
    return blob_response(service, digest, "text/plain; charset=utf-8", None)


@router.post(
    "/api/trials/{trial_id}/rerun",
    status_code=201,
    tags=["trials"],
    response_model=TrialDetail,
    responses=responses(401, 403, 404, 429),
)
def rerun(trial_id: Id, request: Request, service: Lab, app: App, user: Writer) -> JSONResponse:
    """Queue a new trial from the same commit, task, parameters and seed."""
    new_id = service.submissions.rerun(user, trial_id)
    app.on_submit()
    return _created(service, new_id, request)


@router.post(
    "/api/trials/{trial_id}/cancel", tags=["trials"], responses=responses(401, 403, 404, 409)
)
def cancel(trial_id: Id, request: Request, service: Lab, user: Writer) -> CancelView:
    """Cancel a queued trial, or stop a running one (its worker ends it shortly).

    ``done`` says which: ``cancelled``, ``stopping``, or ``ended`` when the trial had
    ended already and nothing was done; ``trial`` is the trial after the call. An
    evaluation's episode is cancelled only with its evaluation (409).
    """
    done = service.queue.cancel(trial_id, user)
    return CancelView(
        done=done, trial=trial_detail(service.index.readable(trial_id), _base(request))
    )


@router.get("/api/commits/{sha}", tags=["archive"], responses=responses(404, 422))
def commit(sha: str, request: Request, service: Lab) -> CommitView:
    """A commit's trials (newest first), each with its reruns and their verdicts."""
    return commit_view(service.index.commit_page(sha), _base(request))


def _created(service: Lab, trial_id: int, request: Request) -> JSONResponse:
    body = trial_detail(service.index.trial(trial_id), _base(request))
    return JSONResponse(
        body.model_dump(mode="json"), status_code=201, headers={"Location": body.url}
    )


def _state(status: Status, outcome: Outcome | None) -> str:
    return f"{status.value}: {outcome.value}" if outcome else status.value


def _epoch(moment: dt.datetime | None) -> float | None:
    if moment is None:
        return None
    if moment.tzinfo is None:
        moment = moment.replace(tzinfo=dt.UTC)
    return moment.timestamp()
