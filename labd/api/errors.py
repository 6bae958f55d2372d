"""How the lab's HTTP port turns exceptions into answers: one table, one body.

Each expected error of the lab's packages maps to an HTTP status here (``STATUS``), and
``problem`` says what the lab answers to it: the status, the words, the headers
(``Retry-After``, or where a redirect goes). The API sends it as ``{"error": "..."}``
(``ErrorBody``); the pages show the same status and words as a page (``labd.web.problems``).
So handlers raise what went wrong and never build error responses themselves. A 5xx is
logged with its traceback (a 503, "not ready", in one line); anything not in the table
is a bug: a 500 whose body says so, logged with its traceback.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from fastapi import APIRouter, FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from fastapi.routing import APIRoute
from starlette.exceptions import HTTPException

from labd.api.models import ErrorBody
from labd.errors import GitFailed, HostedError, NotHosted, UnknownTaskError
from labd.playground import NoNode, PlaygroundError
from repository.errors import (
    AccountError,
    ArchiveError,
    BadCredentials,
    BlobError,
    BlobNotFound,
    HeldOut,
    IndexLost,
    NotYourReservation,
    OverLimit,
    RecordNotFound,
    ReservationError,
    SlotTaken,
)
from scheduler.errors import (
    Busy,
    EpisodeOfEvaluation,
    FilingRefused,
    InvalidRequest,
    LegOfMatch,
    NotYours,
    OverBudget,
    QuotaExceeded,
    RepositoryError,
    TooLarge,
    TrialError,
)

log = logging.getLogger("labd.api")


class ApiError(Exception):
    """An error the API (or a page) itself decides, with its status, any headers its
    answer carries, and the heading a page shows above it (``title``; else the pages'
    own for its status)."""

    def __init__(
        self,
        status: int,
        message: str,
        *,
        headers: Mapping[str, str] | None = None,
        title: str | None = None,
    ) -> None:
        self.status = status
        self.message = message
        self.headers = dict(headers or {})
        self.title = title
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


class Invalid(ApiError):
    """A request that names something wrong: a field, a parameter, a date."""

    def __init__(self, message: str) -> None:
        super().__init__(422, message)


class TooMany(ApiError):
    """Too many failed attempts (keys, passwords): wait ``retry_after`` seconds."""

    def __init__(self, message: str, retry_after: float) -> None:
        self.retry_after = retry_after
        super().__init__(429, message)


# The most specific class wins (a TooLarge is a RepositoryError, but a 413).
STATUS: dict[type[Exception], int] = {
    RecordNotFound: 404,
    HeldOut: 403,  # an episode of a held-out suite: the operator's until it is retired
    BlobNotFound: 404,
    UnknownTaskError: 404,
    NoNode: 503,  # the lab's machine has no Node.js to parse a script with
    PlaygroundError: 422,  # a script that does not parse, or is too large
    NotHosted: 404,  # no such hosted repository, or commit in it
    GitFailed: 500,  # git failed on the lab's own repository: the lab's fault
    HostedError: 422,  # a repository's name or a file's path the lab does not take
    BlobError: 500,  # a blob that no longer matches its digest: the store is damaged
    IndexLost: 503,  # the index's files changed under the lab: writes wait for a restart
    ArchiveError: 422,
    NotYours: 403,
    EpisodeOfEvaluation: 409,  # cancelled only with its evaluation
    LegOfMatch: 409,  # cancelled only with its match
    OverBudget: 429,  # a held-out suite's budget of evaluations
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
    403: "the user may not do this, or may not see it (a held-out episode; or a signed-in"
    " page's request lacks its CSRF token)",
    404: "no such trial, commit, task, reservation, record or file",
    409: (
        "a conflict: the slot is booked already, the client's version is not the lab's, or"
        " an evaluation's episode is cancelled with its evaluation only"
    ),
    413: "too large: a body over its route's limit (1 MiB for JSON), or a repository",
    422: "the request names something wrong (the message says what)",
    429: (
        "over a limit the operator set (a daily limit, a held-out suite's budget), or too"
        " many failed attempts (see Retry-After)"
    ),
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


@dataclass(frozen=True)
class Problem:
    """What the lab answers to an error: its status, its words, its headers."""

    status: int
    message: str
    headers: dict[str, str] = field(default_factory=dict)


def expected(err: BaseException) -> bool:
    """Whether the table knows ``err`` (else it is a bug)."""
    if isinstance(err, ApiError | HTTPException | RequestValidationError):
        return True
    return any(cls in STATUS for cls in type(err).__mro__)


def status_of(err: Exception) -> int:
    if isinstance(err, ApiError):
        return err.status
    for cls in type(err).__mro__:
        if cls in STATUS:
            return STATUS[cls]
    return 500


def problem(err: Exception, method: str = "", path: str = "") -> Problem:
    """What the lab answers to ``err`` (raised by a ``method`` request to ``path``): its
    status from the table, its words, its headers; a bug is a 500 that says so. Nothing
    is logged here (``told``)."""
    if isinstance(err, RequestValidationError):
        problems = list(err.errors())
        if any(p.get("type") == "json_invalid" for p in problems):
            return Problem(400, MEANING[400])
        return Problem(422, invalid(problems))
    if isinstance(err, HTTPException):  # Starlette's own refusals, a body over its limit
        message = str(err.detail)
        if err.status_code == 404 and path:
            message = f"no such page or API route: {path}"
        elif err.status_code == 405 and path:
            message = f"{path} does not take {method}"
        return Problem(err.status_code, message, dict(err.headers or {}))
    if not expected(err):
        text = f"the lab failed to answer ({type(err).__name__}); its log has the details"
        return Problem(500, text)
    message = err.message if isinstance(err, ApiError) else str(err)
    headers = dict(err.headers) if isinstance(err, ApiError) else {}
    if isinstance(err, TooMany | Busy):
        headers["Retry-After"] = str(max(1, round(err.retry_after)))
    return Problem(status_of(err), message, headers)


def told(err: Exception, said: Problem, method: str, path: str) -> None:
    """Log what the operator must hear of an answer: a bug, or a fault of the lab's own
    (5xx), with its traceback; "not ready" (503) and a limit's time running out (504)
    in one line."""
    if not expected(err):
        log.error("%s %s failed", method, path, exc_info=err)
    elif said.status == 503:  # said loudly once where it was found, not per request
        log.warning("%s %s refused: the lab is not ready", method, path)
    elif said.status == 504:  # the limit did its work: nothing of the lab's is broken
        log.warning("%s %s: %s", method, path, said.message)
    elif said.status >= 500:
        log.error("%s %s: %s", method, path, said.message, exc_info=err)


def invalid(problems: Sequence[Mapping[str, Any]]) -> str:
    """Pydantic's problems with a request in one line: ``where: what; ...``."""
    parts = []
    for p in problems:
        where = ".".join(str(x) for x in p.get("loc", ()) if x not in ("body", "query", "path"))
        parts.append(f"{where}: {p.get('msg', 'invalid')}" if where else p.get("msg", ""))
    return "; ".join(parts)


def answer(path: str, method: str, err: Exception) -> JSONResponse:
    """The API's answer to ``err``: the table's status and headers, ``ErrorBody``."""
    said = problem(err, method, path)
    told(err, said, method, path)
    return JSONResponse({"error": said.message}, status_code=said.status, headers=said.headers)


async def _answer(request: Request, err: Exception) -> JSONResponse:
    return answer(request.url.path, request.method, err)


def declare_validation(router: APIRouter) -> APIRouter:
    """Say in the OpenAPI document that a route with parameters answers a malformed one
    with 422 and ``ErrorBody`` (what ``problem`` says), not FastAPI's own shape, that
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
    """Register the table's handlers on ``app``: every error, expected or a bug, is
    answered by ``answer``."""
    known: list[type[Exception]] = [ApiError, *STATUS, RequestValidationError, HTTPException]
    for cls in known:
        app.add_exception_handler(cls, _answer)
    app.add_exception_handler(Exception, _answer)
