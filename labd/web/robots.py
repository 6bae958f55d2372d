"""The live robots' pages: the list of them, and each robot's own page.

    GET /robots                     the live robots: their task, who drives, the seed
    GET /robots/{name}              the robot's page (?interface=video|perception to
                                    choose the variant; ?key=K for a keyed bridge)
    GET /api/robots                 the same list, as JSON
    GET /api/robots/{name}/scene    the robot's model now, to draw and pose in 3D

A robot's page is a roslibjs application (``static/live/``): it reaches its robot
through the bridge like any other client, never through this server. The server only
renders the page with what the script needs to start: the bridge's address, a session
id, who the viewer is, and which interface this session is shown. Sessions of the
maze robot are assigned one of two interfaces at random, A (``video``: the camera) or
B (``perception``: the tag detections and the robot's own sensing, no video), in the
ratio ``labd serve --interface-ratio`` sets; ``?interface=`` overrides it for
experimenters. The page sends the assignment as its drive's ``interface``
(``/lab/drive``) and as a user-experience event, so both land in the record.
"""

from __future__ import annotations

import secrets

from fastapi import APIRouter, Request
from fastapi.responses import HTMLResponse, Response
from pydantic import BaseModel

from labd.api.common import Lab
from labd.api.errors import ApiError, responses
from labd.api.site import RobotLink, Site
from labd.api.state import App
from labd.sim import registry
from labd.sim.registry import Console, TaskSpec
from labd.web.matches import short
from labd.web.problems import PageRoute
from labd.web.render import page
from labd.web.session import Viewer

router = APIRouter(include_in_schema=False, route_class=PageRoute)
api = APIRouter(tags=["robots"])


class RobotState(BaseModel):
    """A live robot as its pages show it (``/lab/driver`` and ``/lab/episode`` say the
    same through the bridge, and change as they speak)."""

    name: str
    task: str
    live: bool  # on the wall clock (False: stepped by /lab/step)
    page: str  # its page on this server
    bridge: str  # its graph on the bridge (ws:// or wss://)
    driver: str  # who drives it ("" when nobody does)
    session: str
    interface: str
    seed: int  # the episode now
    recording: bool  # the drive is being recorded as a demonstration


class LiveScene(BaseModel):
    """A live robot's model now (``labd.recorder.scene.live`` describes every field)."""

    bodies: list[dict[str, object]]
    geoms: list[dict[str, object]]
    textures: list[str]
    qpos: list[float]
    rest: list[float]
    joints: dict[str, int]
    root: str
    odom: list[float]
    seed: int


def bridge_url(request: Request, lab: Site, name: str) -> str:
    """Where a page reaches robot ``name``: the host it was served from, at the bridge's
    port; ``wss://`` when the bridge has its own certificate, or when the page came over
    https (a TLS proxy in front of both ports: browsers refuse ws:// from such a page)."""
    host = request.url.hostname or "127.0.0.1"
    host = f"[{host}]" if ":" in host else host
    scheme = "wss" if lab.bridge_tls or request.url.scheme == "https" else "ws"
    port = lab.bridge_port if lab.bridge_port is not None else 9090
    return f"{scheme}://{host}:{port}/robots/{name}"


def state(request: Request, lab: Site, robot: RobotLink) -> RobotState:
    drive = lab.drives.get(robot.name)
    current = drive.current if drive is not None else None
    return RobotState(
        name=robot.name,
        task=robot.task,
        live=robot.live,
        page=str(request.url_for("robot_page", name=robot.name)),
        bridge=bridge_url(request, lab, robot.name),
        driver=current.user if current else "",
        session=current.session if current else "",
        interface=current.interface if current else "",
        seed=drive.robot.sim.seed if drive is not None else 0,
        recording=bool(current and current.recorder),
    )


def _robot(lab: Site, name: str) -> RobotLink:
    """The live robot ``name`` (404 naming those there are, if there is none)."""
    found = next((r for r in lab.robots if r.name == name), None)
    if found is None:
        names = ", ".join(r.name for r in lab.robots) or "none"
        message = f"no live robot {name!r} here; this lab's live robots: {names}"
        raise ApiError(404, message, title=f"No robot {name}")
    return found


def assign(lab: Site, console: Console, asked: str | None) -> tuple[str, str]:
    """The interface a new session is shown, and how it was chosen: ``override`` (the
    page's ``?interface=``), ``random`` (drawn in the lab's ratio) or ``only``."""
    if asked:
        if asked not in console.interfaces:
            choices = " or ".join(console.interfaces)
            message = f"interface {asked!r}: this robot's page shows {choices}"
            raise ApiError(422, message, title="No such interface")
        return asked, "override"
    if len(console.interfaces) == 1:
        return console.interfaces[0], "only"
    first, second = console.interfaces[:2]
    return (first if lab.rng.random() < lab.interface_ratio else second), "random"


@router.get("/robots", response_class=HTMLResponse)
def robots(request: Request, app: App, service: Lab, viewer: Viewer) -> HTMLResponse:
    lab = app.site
    states = [state(request, lab, r) for r in lab.robots]
    context = {
        "robots": states,
        "reservations": lab.reservations,
        "matches": service.matches.under_way(),  # teams playing each other, in sandboxes
        "short": short,
    }
    return page(request, "robots.html", context, user=viewer)


@router.get("/robots/{name}", response_class=HTMLResponse, name="robot_page")
def robot_page(
    request: Request, name: str, app: App, viewer: Viewer, interface: str | None = None
) -> HTMLResponse:
    lab = app.site
    robot = _robot(lab, name)
    console = registry.get(robot.task).console
    shown, assigned = assign(lab, console, interface)
    config = {
        "robot": robot.name,
        "task": robot.task,
        "bridge": bridge_url(request, lab, robot.name),
        "session": secrets.token_hex(6),
        "user": viewer.name if viewer is not None else "guest",
        "signed_in": viewer is not None,
        "reservations": lab.reservations,
        "interface": shown,
        "assigned": assigned,
        "ratio": lab.interface_ratio,
        "interfaces": list(console.interfaces),
        "scene": str(request.url_for("robot_scene", name=robot.name)),
        **_generic(registry.get(robot.task)),
    }
    return page(
        request,
        console.template,
        {"robot": state(request, lab, robot), "config": config, "interface": shown},
        user=viewer,
    )


PLOTTED = ("std_msgs/msg/Float64", "std_msgs/msg/Float64MultiArray")


def _generic(spec: TaskSpec) -> dict[str, object]:
    """What the generic page needs of a task: its action vector, its numeric topics."""
    observations = spec.task_class.observations if spec.task_class is not None else ()
    return {
        "actions": spec.actions.describe() if spec.actions is not None else None,
        "plots": [(o.name, o.type) for o in observations if o.type in PLOTTED],
    }


@api.get("/api/robots", response_model=list[RobotState])
def robot_list(request: Request, app: App) -> list[RobotState]:
    """The live robots this lab hosts: their task, their bridge address, who drives
    each and the episode's seed."""
    return [state(request, app.site, r) for r in app.site.robots]


@api.get(
    "/api/robots/{name}/scene",
    name="robot_scene",
    response_class=Response,
    responses={200: {"model": LiveScene, "description": "the model now"}, **responses(404)},
)
async def robot_scene(name: str, app: App) -> Response:
    """The live robot's model as it is now, to draw in 3D (bodies, geoms, textures) and
    pose from its topics (``/joint_states``, ``/tf``): each episode has its own model."""
    drive = app.site.drives.get(name)
    if drive is None:
        raise ApiError(404, f"no live robot {name} here")
    return Response(
        await app.scenes.scene(app.site, drive),
        media_type="application/json",
        headers={"Cache-Control": "no-store"},
    )
