"""Who is looking at a page, and what they may do from it.

A person signs in (``labd.web.forms``) with their password, or by pasting an API token
once; the lab then keeps a **session**: a random id in a cookie that the pages' scripts
cannot read (HttpOnly), sent to this lab only, and only on requests that start from its
own pages (SameSite=Strict); the index keeps only its hash (``repository.accounts``).

Every form that changes something carries a **CSRF token** (a hidden ``csrf`` field):
the signed-in session's own, or, before signing in, a random one also kept in a cookie
(double submit). A form whose token is missing or does not match is refused with a
page saying to reload it; the form must also come from one of the lab's pages
(``Origin``, else ``Referer``). The pages' scripts send the same token to the API in
``X-CSRF-Token`` (``<meta name="csrf-token">`` in every page).

Who is looking is a dependency: ``Viewer`` (the person, or None) on pages for anyone,
``Person`` (or ``SignedIn(then)``) on pages and forms for signed-in people, which
sends anyone else to the sign-in page (``SignInFirst``, a 303), and back once signed in.
"""

from __future__ import annotations

import secrets
from typing import Annotated
from urllib.parse import quote, urlsplit

from fastapi import Depends, Request
from starlette.responses import Response

from labd.api.common import SESSION_COOKIE, Lab, web_session
from labd.api.errors import ApiError, Forbidden
from repository.accounts import same
from repository.index import User

CSRF_COOKIE = "labd_csrf"  # before signing in: the double-submitted token
CSRF_FIELD = "csrf"


def _viewer(request: Request, service: Lab) -> User | None:
    session = web_session(service, request)
    request.state.viewer = session.user if session is not None else None  # error pages
    if session is not None:
        request.state.csrf = session.csrf
        return session.user
    token = request.cookies.get(CSRF_COOKIE, "")
    if len(token) < 24:
        token = secrets.token_urlsafe(24)
        request.state.new_csrf = token  # the page sets the cookie (labd.web.render)
    request.state.csrf = token
    return None


Viewer = Annotated[User | None, Depends(_viewer)]


class SignInFirst(ApiError):
    """A page or form for signed-in people, asked by someone who is not: a 303 to the
    sign-in page, which comes back to ``then`` (a page of this lab) once signed in."""

    def __init__(self, then: str) -> None:
        self.then = then
        where = f"/session?then={quote(then, safe='/')}"
        super().__init__(303, "sign in first", headers={"Location": where})


class SignedIn:
    """The dependency of a page or form for signed-in people: the person, else
    ``SignInFirst``. It comes back to ``then`` (formatted with the path's parameters:
    ``"/trials/{trial_id}"``), by default the page asked for; a form posted to an
    address of its own names the page it is on."""

    def __init__(self, then: str | None = None) -> None:
        self.then = then

    def __call__(self, request: Request, viewer: Viewer) -> User:
        if viewer is not None:
            return viewer
        if self.then is not None:
            raise SignInFirst(self.then.format(**request.path_params))
        query = f"?{request.url.query}" if request.url.query else ""
        raise SignInFirst(request.url.path + query)


Person = Annotated[User, Depends(SignedIn())]


def same_origin(request: Request) -> None:
    """Refuse a form posted from another site (``Forbidden``)."""
    source = request.headers.get("origin") or request.headers.get("referer")
    if source is None:
        return  # not a browser's cross-site form (those always say where they come from)
    theirs = urlsplit(source)
    if (theirs.scheme, theirs.netloc) != (request.url.scheme, request.url.netloc):
        raise Forbidden("this form must be sent from the lab's own pages")


async def csrf_checked(request: Request, service: Lab) -> None:
    """Refuse a form without the CSRF token of the session (or of the visitor)."""
    same_origin(request)
    form = await request.form()
    sent = form.get(CSRF_FIELD)
    if not isinstance(sent, str) or not sent:
        raise ApiError(
            403,
            "The lab acts only on forms from its own pages, which carry a token proving it."
            " Reload the page and send the form again.",
            title="This form had no CSRF token",
        )
    session = web_session(service, request)
    expected = session.csrf if session is not None else request.cookies.get(CSRF_COOKIE, "")
    if not expected or not same(sent, expected):
        raise ApiError(
            403,
            "Its CSRF token is not your session's (you may have signed in or out since the"
            " page was loaded, or in another tab). Reload the page and send it again.",
            title="This form has expired",
        )


CsrfChecked = Depends(csrf_checked)
SameOrigin = Depends(same_origin)


def set_session_cookie(response: Response, request: Request, value: str, max_age: float) -> None:
    """Keep the session id in the browser: HttpOnly, SameSite=Strict, Secure on https."""
    response.set_cookie(
        SESSION_COOKIE,
        value,
        max_age=int(max_age),
        httponly=True,
        samesite="strict",
        secure=request.url.scheme == "https",
    )
