"""The lab's web pages, served beside the HTTP API: the archive to browse (``pages``),
forms to sign in, submit and rerun (``forms``), accounts and tokens (``accounts``),
reservations and the robots' calendars (``reservations``), the live robots' pages
(``robots``), and the API's own documentation (``/docs``, ``/redoc``), every script and
style served by the lab (``render``), every answer with the headers that keep other
sites out (``headers``)."""

from __future__ import annotations

from collections.abc import Callable

from fastapi import FastAPI, Request
from fastapi.responses import HTMLResponse

from labd.api.app import create_app as create_api
from labd.service import Service
from labd.web import accounts, forms, pages, reservations, robots
from labd.web.assets import Precompressed
from labd.web.headers import SecurityHeaders
from labd.web.render import STATIC, RobotLink, Site, page
from labd.web.session import FormRefused

__all__ = ["RobotLink", "Site", "create_app", "install"]


def create_app(
    service: Service, site: Site | None = None, *, on_submit: Callable[[], None] | None = None
) -> FastAPI:
    """The lab's whole HTTP face: the API over ``service`` and the pages."""
    site = site or Site()
    app = create_api(service, on_submit=on_submit, robots=[r.name for r in site.robots if r.live])
    install(app, site)
    return app


def install(app: FastAPI, site: Site) -> None:
    """Add the pages, the static files and offline API docs to ``app``."""
    app.state.site = site
    app.mount("/static", Precompressed(directory=STATIC), name="static")
    app.include_router(pages.router)
    app.include_router(forms.router)
    app.include_router(robots.router)
    app.include_router(robots.api)
    app.include_router(accounts.router)
    app.include_router(reservations.router)

    @app.exception_handler(FormRefused)
    def refused(request: Request, err: FormRefused) -> HTMLResponse:
        context = {"title": err.title, "message": err.message, "back": request.url.path}
        return page(request, "error.html", context, status_code=err.status)

    @app.get("/docs", include_in_schema=False)
    def swagger(request: Request) -> HTMLResponse:
        return page(request, "docs.html", {})

    @app.get("/redoc", include_in_schema=False)
    def redoc(request: Request) -> HTMLResponse:
        return page(request, "redoc.html", {})

    app.add_middleware(SecurityHeaders)
