"""The playground's pages: write a roslibjs script, run it live, or run it as a trial.

    GET /playground                 the editor (?task=, ?robot=, or ?repo=USER/NAME&commit=
                                    to open a committed script)
    GET /playground/runner          the frame a script runs in, live (the page's own)

The script runs live inside ``/playground/runner``, framed by the playground page with
``sandbox="allow-scripts"``: an opaque origin, so the script reaches the robot's bridge
and nothing of the signed-in person's (no cookies, no CSRF token, no lab API as them).
The runner's own Content-Security-Policy lets it run the script (a ``blob:`` module),
load roslibjs from the lab, and connect to the bridge, and nothing else. The page sends
the script and the robot's address (with the person's slot key under reservations) to
the frame, and shows what the script prints. Stopping removes the frame, which closes
the script's connection: the drive ends and is filed as any drive is.
"""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Request
from fastapi.responses import HTMLResponse

from labd.api.common import Lab
from labd.api.errors import ApiError
from labd.api.playground import playground_script
from labd.api.state import App
from labd.playground import template
from labd.sim import registry
from labd.web.problems import PageRoute
from labd.web.render import page
from labd.web.robots import bridge_url
from labd.web.session import Viewer

router = APIRouter(include_in_schema=False, route_class=PageRoute)


@router.get("/playground", response_class=HTMLResponse)
def playground(  # noqa: PLR0917 (a page's query, each its own parameter)
    request: Request,
    service: Lab,
    app: App,
    viewer: Viewer,
    task: str | None = None,
    robot: str | None = None,
    repo: str | None = None,
    commit: str | None = None,
) -> HTMLResponse:
    site = app.site
    opened: dict[str, Any] | None = None
    if repo is not None:
        user, _, name = repo.partition("/")
        found = playground_script(service, user, name, commit)
        opened = found.model_dump()
        task = found.task
    elif robot is not None:
        link = next((r for r in site.robots if r.name == robot), None)
        if link is None:
            raise ApiError(404, f"no live robot {robot!r} here", title=f"No robot {robot}")
        task = link.task
    tasks = registry.names()
    task = task or (site.robots[0].task if site.robots else tasks[0])
    registry.get(task)  # 404 for an unknown task, naming the known ones
    robots = [
        {"name": r.name, "bridge": bridge_url(request, site, r.name)}
        for r in site.robots
        if r.task == task and r.live
    ]
    config = {
        "task": task,
        "robots": robots,
        "robot": robot or (robots[0]["name"] if robots else None),
        "signed_in": viewer is not None,
        "user": viewer.name if viewer is not None else None,
        "reservations": site.reservations,
        "opened": opened,
        "name": opened["name"] if opened else task,
        "template": template(task),
        "suites": [suite.name for suite in registry.get(task).suites],
    }
    return page(
        request,
        "playground.html",
        {"config": config, "tasks": tasks, "task": task, "opened": opened},
        user=viewer,
    )


@router.get("/playground/runner", response_class=HTMLResponse)
def runner(request: Request, app: App) -> HTMLResponse:
    """The frame a script runs in (module docstring), with its own policy."""
    origin = str(request.base_url).rstrip("/")
    nonce = getattr(request.state, "csp_nonce", "")
    host = request.url.hostname or "127.0.0.1"
    host = f"[{host}]" if ":" in host else host
    port = app.site.bridge_port if app.site.bridge_port is not None else 9090
    policy = "; ".join(
        [
            "default-src 'none'",
            f"script-src 'nonce-{nonce}' 'wasm-unsafe-eval' blob: {origin}/static/vendor/roslib/",
            f"connect-src ws://{host}:{port} wss://{host}:{port}",
            f"frame-ancestors {origin}",
            "base-uri 'none'",
            "form-action 'none'",
        ]
    )
    response = page(request, "playground_runner.html", {"origin": origin})
    response.headers["Content-Security-Policy"] = policy
    response.headers["X-Frame-Options"] = "SAMEORIGIN"
    response.headers["Cache-Control"] = "no-store"
    return response
