"""Rendering the lab's pages: one Jinja2 environment, its filters, and the page shell.

Every value a user controls (repository URLs, refs, parameters, a controller's output)
reaches a page through Jinja2 with autoescaping on, so what a controller prints is
shown, never run. Scripts and styles come from ``/static`` only (``web/build.mjs`` puts
the npm packages there at set-up), so the pages work with no internet.
"""

from __future__ import annotations

import datetime as dt
import json
import math
from pathlib import Path
from typing import Any

from fastapi import Request
from fastapi.templating import Jinja2Templates
from starlette.responses import HTMLResponse

from labd import __version__
from labd.web.session import CSRF_COOKIE
from repository.formats import FORMATS
from repository.index import User
from repository.trial import Outcome, Status
from repository.units import moment

HERE = Path(__file__).resolve().parent
STATIC = HERE / "static"
VENDOR = STATIC / "vendor"


def when(moment: dt.datetime | None) -> str:
    return moment.strftime("%Y-%m-%d %H:%M:%S UTC") if moment else "-"


def number(value: Any) -> str:
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        return f"{value:.4g}" if math.isfinite(value) else str(value)
    return str(value) if value is not None else "-"


def seconds(value: float | None) -> str:
    if value is None:
        return "-"
    return f"{value:.1f} s" if value < 120 else f"{value / 60:.1f} min"


def state(status: Status, outcome: Outcome | None) -> str:
    """The word a trial's badge shows: its outcome once finished, else its status."""
    return outcome.value if outcome is not None else status.value


def pretty(value: Any) -> str:
    return json.dumps(value, indent=2, sort_keys=True, ensure_ascii=False)


templates = Jinja2Templates(directory=str(HERE / "templates"))


def epoch(value: float | None) -> str:
    """An epoch time as pages show it (UTC)."""
    return when(None if value is None else moment(value))


def hhmm(value: float) -> str:
    return moment(value).strftime("%H:%M")


templates.env.filters.update(
    when=when, number=number, seconds=seconds, pretty=pretty, epoch=epoch, hhmm=hhmm
)
templates.env.globals.update(state=state, version=__version__)
templates.env.globals["export_formats"] = tuple(FORMATS.values())  # a trial's downloads


def page(
    request: Request,
    name: str,
    context: dict[str, Any],
    *,
    user: User | None = None,
    status_code: int = 200,
) -> HTMLResponse:
    """Render template ``name`` with the page shell's context (and the CSRF token its
    forms carry: ``labd.web.session``)."""
    response = templates.TemplateResponse(
        request,
        name,
        {
            "user": user,
            "vendor_ready": (VENDOR / "README").exists(),
            "viewer_ready": (STATIC / "record.js").exists(),
            "csrf": getattr(request.state, "csrf", ""),
            "csp_nonce": getattr(request.state, "csp_nonce", ""),  # labd.web.headers
            **context,
        },
        status_code=status_code,
    )
    fresh = getattr(request.state, "new_csrf", None)
    if fresh:
        response.set_cookie(
            CSRF_COOKIE,
            fresh,
            httponly=True,
            samesite="strict",
            secure=request.url.scheme == "https",
        )
    return response
