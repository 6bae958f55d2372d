"""What the API's routers share: the service, who is asking and from where, serving
blobs.

A request writes as a user when it carries a token (``Authorization: Bearer TOKEN``,
for scripts and the ``labd`` commands) or comes from a signed-in page: the session
cookie the pages set, and, for anything but reading, the session's CSRF token in
``X-CSRF-Token`` (the pages put it in ``<meta name="csrf-token">``), so that another
site cannot make a signed-in browser write.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from typing import Annotated

from fastapi import Depends, Request
from fastapi.responses import StreamingResponse
from fastapi.security import APIKeyCookie, HTTPAuthorizationCredentials, HTTPBearer

from labd.api.errors import Forbidden, Unauthorized
from labd.api.state import App, state_of
from labd.api.throttle import Attempts
from labd.service import Service
from repository.accounts import WebSession, same
from repository.index import User

log = logging.getLogger("labd.api")
bearer = HTTPBearer(
    auto_error=False, description="a token: `labd users add NAME`, or the tokens page"
)
SESSION_COOKIE = "labd_session"
CSRF_HEADER = "X-CSRF-Token"
SAFE = frozenset({"GET", "HEAD", "OPTIONS"})
session_cookie = APIKeyCookie(
    name=SESSION_COOKIE,
    auto_error=False,
    description="a signed-in page's session; writing also needs its X-CSRF-Token header",
)


def _service(request: Request) -> Service:
    return state_of(request.app).service


Lab = Annotated[Service, Depends(_service)]


def client_address(request: Request) -> str:
    """The address a request came from, as the throttles count it: the socket's peer,
    or the address a trusted proxy (``labd serve --trusted-proxy``) put in
    ``X-Forwarded-For``; never that header from anyone else (``labd.api.server``)."""
    return request.client.host if request.client else "unknown"


async def _attempts(request: Request, app: App) -> Attempts:
    return Attempts(app.throttle, client_address(request))


# Who is asking, by address, and their failed attempts there (``labd.api.throttle``).
Caller = Annotated[Attempts, Depends(_attempts)]


def web_session(service: Service, request: Request) -> WebSession | None:
    """The signed-in session of the request's cookie, if it has a live one."""
    cookie = request.cookies.get(SESSION_COOKIE)
    return service.accounts.session(cookie) if cookie else None


def identify(
    service: Service, method: str, token: str | None, cookie: str | None, csrf: str
) -> User:
    """The user a write comes from: its token, else its signed-in session (whose CSRF
    token ``csrf`` must be, for anything but reading); ``Unauthorized`` or ``Forbidden``
    saying what to do. ``labd.api.edges`` asks this before a body is read, the routes'
    ``Writer`` again."""
    if token is not None:
        user = service.index.user_by_token(token)
        if user is None:
            raise Unauthorized(
                "the token is not valid here (unknown or revoked); make a new one on the"
                " tokens page, or ask the operator"
            )
        return user
    if cookie:
        session = service.accounts.session(cookie)
        if session is None:
            raise Unauthorized("your sign-in has ended; sign in again")
        if method not in SAFE and not same(csrf, session.csrf):
            raise Forbidden(
                f"a signed-in page's request must carry its CSRF token in {CSRF_HEADER}"
                " (the page's <meta name=csrf-token>); reload the page and try again"
            )
        return session.user
    raise Unauthorized(
        "this needs a token or a sign-in: send Authorization: Bearer TOKEN "
        "(make one on the tokens page, or the operator makes one with `labd users add "
        "NAME`; labd commands take --token or LABD_TOKEN)",
    )


def _writer(
    request: Request,
    service: Lab,
    credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(bearer)],
    cookie: Annotated[str | None, Depends(session_cookie)],
) -> User:
    token = credentials.credentials if credentials is not None else None
    csrf = request.headers.get(CSRF_HEADER, "")
    return identify(service, request.method, token, cookie, csrf)


Writer = Annotated[User, Depends(_writer)]


def _reader(
    request: Request,
    service: Lab,
    credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(bearer)],
    cookie: Annotated[str | None, Depends(session_cookie)],
) -> User | None:
    """Who reads: the token's or the signed-in session's user, or None for anyone."""
    token = credentials.credentials if credentials is not None else None
    if token is None and not cookie:
        return None
    return identify(service, request.method, token, cookie, "")


Reader = Annotated[User | None, Depends(_reader)]


def blob_response(
    service: Service, digest: str, media_type: str, filename: str | None
) -> StreamingResponse:
    """Stream a blob, checked against its digest first (a damaged one is never sent)."""
    store = service.store
    store.verify(digest)  # BlobNotFound: 404; BlobCorrupt: 500, logged (labd.api.errors)

    def chunks() -> Iterator[bytes]:
        yield from store.iter_chunks(digest)

    headers = {"ETag": f'"{digest}"', "Cache-Control": "public, max-age=31536000, immutable"}
    if filename:
        headers["Content-Disposition"] = f'attachment; filename="{filename}"'
    headers["Content-Length"] = str(store.size(digest))
    return StreamingResponse(chunks(), media_type=media_type, headers=headers)
