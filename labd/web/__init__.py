"""The lab's web pages, served beside the HTTP API: the archive to browse (``pages``),
evaluations followed, compared and ranked (``evaluations``), benchmarks and their
runs ranked (``benchmarks``), matches followed and
their ladders (``matches``), forms to sign in, submit and rerun (``forms``), accounts
and tokens (``accounts``), reservations and the robots' calendars (``reservations``),
the live robots' pages (``robots``), and the API's own documentation (``/docs``,
``/redoc``), every script and style served by the lab (``render``), every answer with
the headers that keep other sites out (``headers``). A page answers an error as the
API's table says, as a page (``problems``); who is looking is a dependency
(``session``)."""

from __future__ import annotations

from collections.abc import Callable

from fastapi import APIRouter, FastAPI, Request
from fastapi.responses import HTMLResponse
from starlette.exceptions import HTTPException
from starlette.responses import Response

from labd.api import errors
from labd.api.app import create_app as create_api
from labd.api.site import RobotLink, Site
from labd.service import Service
from labd.web import (
    accounts,
    benchmarks,
    evaluations,
    forms,
    matches,
    oidc,
    pages,
    playground,
    reservations,
    robots,
)
from labd.web.assets import Precompressed
from labd.web.headers import SecurityHeaders
from labd.web.problems import PageRoute, error_page
from labd.web.render import STATIC, page
from repository.reservations import Reservation, load_secret

__all__ = ["RobotLink", "Site", "create_app", "install"]

docs = APIRouter(include_in_schema=False, route_class=PageRoute)


@docs.get("/docs")
def swagger(request: Request) -> HTMLResponse:
    return page(request, "docs.html", {})


@docs.get("/redoc")
def redoc(request: Request) -> HTMLResponse:
    return page(request, "redoc.html", {})


def create_app(
    service: Service,
    site: Site | None = None,
    *,
    on_submit: Callable[[], None] | None = None,
    on_reservation: Callable[[Reservation], None] | None = None,
) -> FastAPI:
    """The lab's whole HTTP face: the API over ``service`` and the pages."""
    site = site or Site()
    app = create_api(
        service,
        site,
        on_submit=on_submit,
        on_reservation=on_reservation,
        robots=[r.name for r in site.robots if r.live],
    )
    install(app)
    public = service.config.public_url or ""
    oidc.install(
        app,
        service.config.oidc,
        load_secret(service.keys / "oidc.secret"),
        https=public.startswith("https://"),
    )
    return app


def install(app: FastAPI) -> None:
    """Add the pages, the static files and offline API docs to ``app`` (an app of
    ``labd.api.app.create_app``, whose state holds the site)."""
    app.mount("/static", Precompressed(directory=STATIC), name="static")
    app.include_router(pages.router)
    app.include_router(evaluations.router)
    app.include_router(benchmarks.router)
    app.include_router(matches.router)
    app.include_router(forms.router)
    app.include_router(robots.router)
    app.include_router(robots.api)
    app.include_router(playground.router)
    app.include_router(accounts.router)
    app.include_router(reservations.router)
    app.include_router(docs)
    app.add_exception_handler(HTTPException, _not_a_page)
    app.add_middleware(SecurityHeaders)


NOT_PAGES = ("/api/", "/git/", "/static/", "/openapi.json")


async def _not_a_page(request: Request, err: Exception) -> Response:
    """A URL that is no route (404) or does not take the method (405): a browser asking
    for a page gets the error page, anything else the API's JSON (``labd.api.errors``)."""
    path = request.url.path
    wants_page = "text/html" in request.headers.get("accept", "")
    if wants_page and not path.startswith(NOT_PAGES) and request.method in ("GET", "HEAD"):
        said = errors.problem(err, request.method, path)
        return error_page(request, err, said)
    return errors.answer(path, request.method, err)
