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

# No "from __future__ import annotations": FastAPI reads the annotations of the
# handlers defined inside create_app at run time, and they name local dependencies.

import datetime as dt
import logging
from collections.abc import Callable, Iterator
from typing import Annotated, Any

from fastapi import Depends, FastAPI, Query, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, StreamingResponse
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from pydantic import BaseModel, ConfigDict, Field

from labd import __version__
from labd.api import views
from labd.service import Service
from labd.sim import registry
from repository.errors import ArchiveError, BlobError, BlobNotFound, RecordNotFound
from repository.index import STATUSES, Filters, User
from scheduler.errors import QueueError, QuotaExceeded, RepositoryError, TooLarge
from scheduler.submit import InvalidRequest

log = logging.getLogger("labd.api")
Value = bool | int | float | str
bearer = HTTPBearer(auto_error=False, description="a token from `labd users add NAME`")


class ApiError(Exception):
    def __init__(self, status: int, message: str) -> None:
        self.status = status
        self.message = message
        super().__init__(message)


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
    index = service.index
    queued = on_submit or service.wake

    @app.exception_handler(ApiError)
    async def api_error(_: Request, err: ApiError) -> JSONResponse:
        return JSONResponse({"error": err.message}, status_code=err.status)

    @app.exception_handler(RequestValidationError)
    async def invalid(_: Request, err: RequestValidationError) -> JSONResponse:
        problems = list(err.errors())
        if any(p.get("type") == "json_invalid" for p in problems):
            return JSONResponse(
                {"error": "the request body is not valid JSON"}, status_code=400
            )
        parts = []
        for p in problems:
            where = ".".join(str(x) for x in p.get("loc", ()) if x != "body")
            parts.append(f"{where}: {p.get('msg', 'invalid')}" if where else p.get("msg", ""))
        return JSONResponse({"error": "; ".join(parts)}, status_code=422)

    def writer(
        credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(bearer)],
    ) -> User:
        if credentials is None:
            raise ApiError(
                401,
                "this needs a token: send Authorization: Bearer TOKEN "
                "(the operator makes one with `labd users add NAME`; "
                "labd commands take --token or LABD_TOKEN)",
            )
        user = index.user_by_token(credentials.credentials)
        if user is None:
            raise ApiError(401, "the token is not valid here; ask the operator for a new one")
        return user

    def base(request: Request) -> str:
        return str(request.base_url).rstrip("/")

    def one(trial_id: int) -> dict[str, Any]:
        try:
            return index.trial(trial_id)
        except RecordNotFound as err:
            raise ApiError(404, str(err)) from None

    @app.get("/api/tasks", tags=["tasks"])
    def tasks() -> dict[str, Any]:
        """The tasks a trial can run, with their parameters."""
        return {"tasks": [views.task(name) for name in registry.names()]}

    @app.post("/api/trials", status_code=201, tags=["trials"])
    def submit(
        body: SubmitRequest, request: Request, user: Annotated[User, Depends(writer)]
    ) -> JSONResponse:
        """Resolve the ref to a commit now, and queue a trial of that commit."""
        try:
            done = service.submissions.submit(
                user,
                repository=body.repository,
                ref=body.ref,
                task=body.task,
                params=body.params,
                seed=body.seed,
            )
        except (InvalidRequest, RepositoryError, QuotaExceeded) as err:
            raise _error(err) from None
        queued()
        row = views.trial(index.trial(done.id), base=base(request))
        return JSONResponse(row, status_code=201, headers={"Location": row["url"]})

    @app.get("/api/trials", tags=["trials"])
    def list_trials(
        request: Request,
        repository: str | None = None,
        commit: str | None = None,
        task: str | None = None,
        status: Annotated[str | None, Query(description=" | ".join(STATUSES))] = None,
        user: str | None = None,
        since: dt.datetime | None = None,
        until: dt.datetime | None = None,
        rerun_of: int | None = None,
        limit: Annotated[int, Query(ge=1, le=500)] = 50,
        before: Annotated[int | None, Query(description="the `next` of the page before")] = None,
    ) -> dict[str, Any]:
        """Trials, newest first, a page at a time."""
        filters = Filters(
            repository=repository,
            commit=commit,
            task=task,
            status=status,
            submitter=user,
            since=_epoch(since),
            until=_epoch(until),
            rerun_of=rerun_of,
        )
        try:
            page = index.find(filters, limit=limit, before=before)
        except ArchiveError as err:
            raise ApiError(422, str(err)) from None
        link = base(request)
        return {"trials": [views.trial(r, base=link) for r in page.items], "next": page.next}

    @app.get("/api/trials/{trial_id}", tags=["trials"])
    def show(trial_id: int, request: Request) -> dict[str, Any]:
        """One trial: what was asked, where it is, what came out, its manifest."""
        return views.trial(one(trial_id), base=base(request), full=True)

    @app.get("/api/trials/{trial_id}/data.mcap", tags=["data"])
    def data(trial_id: int) -> StreamingResponse:
        """The trial's MCAP record, checked against its digest before it is sent."""
        row = one(trial_id)
        if not row["mcap"]:
            raise ApiError(404, f"trial {trial_id} has no record ({row['status']})")
        return _blob(service, row["mcap"], "application/x-mcap", f"trial-{trial_id}.mcap")

    @app.get("/api/trials/{trial_id}/logs/{stream}", tags=["data"])
    def logs(trial_id: int, stream: str) -> StreamingResponse:
        """The controller's ``stdout`` or ``stderr``."""
        if stream not in ("stdout", "stderr"):
            raise ApiError(404, "logs are stdout or stderr")
        row = one(trial_id)
        if not row[stream]:
            raise ApiError(404, f"trial {trial_id} has no {stream} log")
        return _blob(service, row[stream], "text/plain; charset=utf-8", None)

    @app.post("/api/trials/{trial_id}/rerun", status_code=201, tags=["trials"])
    def rerun(
        trial_id: int, request: Request, user: Annotated[User, Depends(writer)]
    ) -> JSONResponse:
        """Queue a new trial from the same commit, task, parameters and seed."""
        one(trial_id)
        try:
            done = service.submissions.rerun(user, trial_id)
        except QuotaExceeded as err:
            raise _error(err) from None
        queued()
        row = views.trial(index.trial(done.id), base=base(request))
        return JSONResponse(row, status_code=201, headers={"Location": row["url"]})

    @app.post("/api/trials/{trial_id}/cancel", tags=["trials"])
    def cancel(
        trial_id: int, request: Request, user: Annotated[User, Depends(writer)]
    ) -> dict[str, Any]:
        """Cancel a queued trial, or stop a running one (its worker ends it shortly)."""
        one(trial_id)
        try:
            service.queue.cancel(trial_id, user)
        except QueueError as err:
            raise ApiError(403, str(err)) from None
        return views.trial(index.trial(trial_id), base=base(request))

    @app.get("/api/commits/{sha}", tags=["archive"])
    def commit(sha: str, request: Request) -> dict[str, Any]:
        """A commit's trials (newest first), each with its reruns and their verdicts."""
        try:
            page = index.commit_page(sha)
        except RecordNotFound as err:
            raise ApiError(404, str(err)) from None
        except ArchiveError as err:
            raise ApiError(422, str(err)) from None
        link = base(request)
        return {
            "commit": page["commit"],
            "repositories": page["repositories"],
            "trials": [
                {
                    **views.trial(row, base=link),
                    "reruns": [
                        views.trial(r, base=link) for r in page["reruns"].get(row["id"], [])
                    ],
                }
                for row in page["trials"]
            ],
            "rerun_counts": page["rerun_counts"],
            "truncated": page["truncated"],
        }

    return app


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


def _blob(
    service: Service, digest: str, media_type: str, filename: str | None
) -> StreamingResponse:
    store = service.store
    try:
        store.verify(digest)
    except BlobError as err:
        log.error("%s", err)
        status = 404 if isinstance(err, BlobNotFound) else 500  # 500: the store is damaged
        raise ApiError(status, str(err)) from None

    def chunks() -> Iterator[bytes]:
        yield from store.iter_chunks(digest)

    headers = {"ETag": f'"{digest}"', "Cache-Control": "public, max-age=31536000, immutable"}
    if filename:
        headers["Content-Disposition"] = f'attachment; filename="{filename}"'
    headers["Content-Length"] = str(store.size(digest))
    return StreamingResponse(chunks(), media_type=media_type, headers=headers)
