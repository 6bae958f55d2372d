"""Who is looking at a page, and what they may do from it.

Until the lab has accounts of its own, a person signs in on a page by pasting their
token once (``labd users add NAME`` makes one); it is kept in a cookie the page's
scripts cannot read (HttpOnly), sent to this lab only, and only on requests that start
from its own pages (SameSite=Strict). Forms that change something also check that the
request comes from one of the lab's pages (``Origin``, else ``Referer``), so another site
cannot make a visitor's browser submit or rerun.
"""

from __future__ import annotations

from typing import Annotated
from urllib.parse import urlsplit

from fastapi import Depends, Request

from labd.api.common import Lab
from labd.api.errors import Forbidden
from repository.index import User

COOKIE = "labd_token"
MAX_AGE = 30 * 24 * 3600  # seconds a sign-in lasts


def _viewer(request: Request, service: Lab) -> User | None:
    token = request.cookies.get(COOKIE)
    if not token:
        return None
    return service.index.user_by_token(token)


Viewer = Annotated[User | None, Depends(_viewer)]


def same_origin(request: Request) -> None:
    """Refuse a form posted from another site (``Forbidden``)."""
    source = request.headers.get("origin") or request.headers.get("referer")
    if source is None:
        return  # not a browser's cross-site form (those always say where they come from)
    theirs = urlsplit(source)
    if (theirs.scheme, theirs.netloc) != (request.url.scheme, request.url.netloc):
        raise Forbidden("this form must be sent from the lab's own pages")


SameOrigin = Depends(same_origin)
