"""How the API turns exceptions into answers: one table, one body.

Each expected error of the lab's packages maps to an HTTP status here, and every error
body is ``{"error": "..."}`` (``ErrorBody``), so handlers raise what went wrong and never
build error responses themselves. A 5xx is logged with its traceback (a 503, "not
ready", in one line); anything not in the table is a bug: a 500 whose body says so,
logged with its traceback.
"""

from __future__ import annotations

import logging
from typing import Any

from fastapi import APIRouter, FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from fastapi.routing import APIRoute
from starlette.exceptions import HTTPException

from labd.api.models import ErrorBody
from repository.errors import (
    AccountError,
    ArchiveError,
    BadCredentials,
    BlobError,
    BlobNotFound,
    IndexLost,
    NotYourReservation,
    OverLimit,
    RecordNotFound,
    ReservationError,
    SlotTaken,
)
from scheduler.errors import (
    Busy,
    FilingRefused,
    InvalidRequest,
    NotYours,
    QuotaExceeded,
    RepositoryError,
    TooLarge,
    TrialError,
)

log = logging.getLogger("labd.api")


class ApiError(Exception):
    """An error the API itself decides, with its status."""

    def __init__(self, status: int, message: str) -> None:
        self.status = status
        self.message = message
        super().__init__(message)


class Unauthorized(ApiError):
    def __init__(self, message: str) -> None:
        super().__init__(401, message)


class Forbidden(ApiError):
    def __init__(self, message: str) -> None:
        super().__init__(403, message)


class Conflict(ApiError):
    def __init__(self, message: str) -> None:
        super().__init__(409, message)


class TooMany(ApiError):
    """Too many failed attempts (keys, passwords): wait ``retry_after`` seconds."""

    def __init__(self, message: str, retry_after: float) -> None:
        self.retry_after = retry_after
        super().__init__(429, message)


# The most specific class wins (a TooLarge is a RepositoryError, but a 413).
STATUS: dict[type[Exception], int] = {
    RecordNotFound: 404,
    BlobNotFound: 404,
    BlobError: 500,  # a blob that no longer matches its digest: the store is damaged
    IndexLost: 503,  # the index's files changed under the lab: writes wait for a restart
    ArchiveError: 422,
    NotYours: 403,
    FilingRefused: 422,
    NotYourReservation: 403,
    SlotTaken: 409,
    OverLimit: 429,
    ReservationError: 422,
    BadCredentials: 401,
    AccountError: 422,
    QuotaExceeded: 429,
    Busy: 503,
    InvalidRequest: 422,
    TooLarge: 413,
    RepositoryError: 422,
    TrialError: 422,
}
MEANING = {
    400: "the request body is not valid JSON",
    401: "no token or sign-in, or one the lab does not know",
    403: "the user may not do this (or a signed-in page's request lacks its CSRF token)",
    404: "no such trial, commit, reservation, record or file",
    409: "a conflict: the slot is booked already, or the client's version is not the lab's",
    413: "too large: a body over its route's limit (1 MiB for JSON), or a repository",
    422: "the request names something wrong (the message says what)",
    429: "over a limit the operator set, or too many failed attempts (see Retry-After)",
    500: "the lab is at fault (the message says what)",
    503: (
        "the lab cannot take it now: it has all the submissions or exports it takes in hand"
        " (see Retry-After), or its index's files changed under it (the message says what to"
        " do)"
    ),
    507: "the lab's storage is full (the message says where)",
}


def responses(*statuses: int) -> dict[int | str, dict[str, Any]]:
    """The ``responses`` of a route: these error statuses, each with ``ErrorBody``."""
    return {s: {"model": ErrorBody, "description": MEANING[s]} for s in statuses}


def status_of(err: Exception) -> int:
    if isinstance(err, ApiError):
        return err.status
    for cls in type(err).__mro__:
        if cls in STATUS:
            return STATUS[cls]
    return 500


def answer(path: str, method: str, err: Exception) -> JSONResponse:
    """The answer to an expected error: its status from the table, ``ErrorBody``."""
    status = status_of(err)
    message = err.message if isinstance(err, ApiError) else str(err)
    if status == 503:  # not ready: said loudly once where it was found, not per request
        log.warning("%s %s refused: the lab is not ready", method, path)
    elif status >= 500:
        log.error("%s %s: %s", method, path, message, exc_info=err)
    headers = {}
    if isinstance(err, TooMany | Busy):
        headers["Retry-After"] = str(max(1, round(err.retry_after)))
    return JSONResponse({"error": message}, status_code=status, headers=headers)


async def _known(request: Request, err: Exception) -> JSONResponse:
    return answer(request.url.path, request.method, err)


def http_answer(err: HTTPException, path: str = "", method: str = "") -> JSONResponse:
    """Starlette's own refusals (no such route, a method a route does not take) and a
    body over its route's limit (``labd.api.edges``), in the lab's ``ErrorBody``."""
    message = str(err.detail)
    if err.status_code == 404 and path:
        message = f"no such page or API route: {path}"
    elif err.status_code == 405 and path:
        message = f"{path} does not take {method}"
    return JSONResponse({"error": message}, status_code=err.status_code, headers=err.headers)


async def _http(request: Request, err: Exception) -> JSONResponse:
    assert isinstance(err, HTTPException)
    return http_answer(err, request.url.path, request.method)


async def _bug(request: Request, err: Exception) -> JSONResponse:
    log.error("%s %s failed", request.method, request.url.path, exc_info=err)
    text = f"the lab failed to answer ({type(err).__name__}); its log has the details"
    return JSONResponse({"error": text}, status_code=500)


async def _invalid(_: Request, err: RequestValidationError) -> JSONResponse:
    problems = list(err.errors())
    if any(p.get("type") == "json_invalid" for p in problems):
        return JSONResponse({"error": MEANING[400]}, status_code=400)
    parts = []
    for p in problems:
        where = ".".join(str(x) for x in p.get("loc", ()) if x not in ("body", "query", "path"))
        parts.append(f"{where}: {p.get('msg', 'invalid')}" if where else p.get("msg", ""))
    return JSONResponse({"error": "; ".join(parts)}, status_code=422)


def declare_validation(router: APIRouter) -> APIRouter:
    """Say in the OpenAPI document that a route with parameters answers a malformed one
    with 422 and ``ErrorBody`` (what ``_invalid`` sends), not FastAPI's own shape, that
    a route with a body answers one over its size limit with 413, and that any route
    answers 503 while the index is not writable."""
    for route in router.routes:
        if not isinstance(route, APIRoute):
            continue
        dependant = route.dependant
        takes = any(
            (d.path_params or d.query_params or d.header_params or d.body_params)
            for d in [dependant, *_all(dependant)]
        )
        if takes and 422 not in route.responses:
            route.responses[422] = responses(422)[422]
        if dependant.body_params and 413 not in route.responses:
            route.responses[413] = responses(413)[413]
        if 503 not in route.responses:  # any route may write to the index (/readyz)
            route.responses[503] = responses(503)[503]
    return router


def _all(dependant: Any) -> list[Any]:
    found = []
    for sub in dependant.dependencies:
        found += [sub, *_all(sub)]
    return found


def install(app: FastAPI) -> None:
    """Register the table's handlers on ``app``."""
    known: list[type[Exception]] = [ApiError, *STATUS]
    for cls in known:
        app.add_exception_handler(cls, _known)
    app.add_exception_handler(RequestValidationError, _invalid)  # type: ignore[arg-type]
    app.add_exception_handler(HTTPException, _http)
    app.add_exception_handler(Exception, _bug)
