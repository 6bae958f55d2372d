"""What a request meets before its route: who writes, and how large a body may be.

FastAPI reads a route's whole body before it resolves the route's dependencies, so a
``Writer`` dependency alone would refuse an anonymous 200 MiB upload only after holding
all of it. ``Edges`` checks first:

1. A write to the API (any method but GET, HEAD and OPTIONS under ``/api/``; every such
   route needs a ``Writer``, a test holds them to it) from a caller with no valid token
   or signed-in session is answered 401 (403 without its CSRF token), with the same
   check the routes make (``labd.api.common.identify``), before a byte of the body is
   read; the connection is closed, so the rest is never sent.
2. A body has a size limit per route (``limit``): ``BODY_LIMIT`` (1 MiB) for every JSON
   body and form, ``MAX_BLOB`` for a worker's blob upload, ``MAX_UPLOAD`` (16 MiB) for a
   git fetch from the lab's hosted repositories (``labd.api.git``). A body over it is
   refused with 413: at once when its Content-Length says so, else as soon as the stream
   passes it.
"""

from __future__ import annotations

import anyio.to_thread
from starlette.datastructures import Headers
from starlette.exceptions import HTTPException
from starlette.requests import HTTPConnection
from starlette.responses import JSONResponse
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from labd.api import errors
from labd.api.common import CSRF_HEADER, SAFE, SESSION_COOKIE, bearer, identify
from labd.api.git import MAX_UPLOAD
from labd.api.state import state_of
from labd.api.workers import MAX_BLOB
from repository.units import GiB, MiB

BODY_LIMIT = MiB  # bytes: a JSON body or a form, on every route but a blob upload
GATED = "/api/"  # writes under here need a writer
# (method, path prefix) -> the body limit of the routes there; BODY_LIMIT elsewhere
LIMITS: dict[tuple[str, str], int] = {
    ("PUT", "/api/blobs/"): MAX_BLOB,
    ("POST", "/git/"): MAX_UPLOAD,
}
CLOSE = {"Connection": "close"}  # the rest of a refused body is never read


def limit(method: str, path: str) -> int:
    """The size limit of the body of a ``method`` request to ``path``, in bytes."""
    for (m, prefix), size in LIMITS.items():
        if method == m and path.startswith(prefix):
            return size
    return BODY_LIMIT


class BodyTooLarge(HTTPException):
    """A body over its route's limit (an HTTPException, so that FastAPI passes it on
    from reading the body to the error table rather than calling it a parse error)."""

    def __init__(self, limit: int) -> None:
        self.limit = limit
        size = f"{limit / GiB:g} GiB" if limit >= GiB else f"{limit / MiB:g} MiB"
        super().__init__(
            413, f"the request's body is larger than this route takes ({size}); send less", CLOSE
        )


class Edges:
    """ASGI middleware: writers first, then the body's size (module docstring)."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope["method"] in SAFE:
            await self.app(scope, receive, send)
            return
        if scope["path"].startswith(GATED):
            refusal = await self._refused(scope)
            if refusal is not None:
                await refusal(scope, receive, send)
                return
        most = limit(scope["method"], scope["path"])
        declared = Headers(scope=scope).get("content-length", "")
        if declared.isdigit() and int(declared) > most:
            too_large = BodyTooLarge(most)
            await errors.answer(scope["path"], scope["method"], too_large)(scope, receive, send)
            return
        seen = 0

        async def counted() -> Message:
            nonlocal seen
            message = await receive()
            if message["type"] == "http.request":
                seen += len(message.get("body", b""))
                if seen > most:
                    raise BodyTooLarge(most)
            return message

        await self.app(scope, counted, send)

    async def _refused(self, scope: Scope) -> JSONResponse | None:
        """The answer to a write from someone who may not write; None if they may."""
        connection = HTTPConnection(scope)
        service = state_of(scope["app"]).service
        credentials = await bearer(connection)
        token = credentials.credentials if credentials is not None else None
        cookie = connection.cookies.get(SESSION_COOKIE)
        csrf = connection.headers.get(CSRF_HEADER, "")
        try:
            await anyio.to_thread.run_sync(identify, service, scope["method"], token, cookie, csrf)
        except Exception as err:
            if errors.status_of(err) == 500:
                raise  # a bug, or a lab fault: the error table's 500 and its log
            response = errors.answer(scope["path"], scope["method"], err)
            response.headers.update(CLOSE)
            if response.status_code == 401:
                response.headers["WWW-Authenticate"] = "Bearer"
            return response
        return None
