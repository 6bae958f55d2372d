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

import asyncio
import copy
import secrets
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, TypeVar

import mujoco
import numpy as np
import orjson
from fastapi import APIRouter, Request
from fastapi.responses import HTMLResponse, Response
from pydantic import BaseModel

from labd.api.errors import ApiError, responses
from labd.live import Driving
from labd.recorder import scene
from labd.sim.simulation import Simulation
from labd.web.pages import missing, site
from labd.web.render import RobotLink, Site, page
from labd.web.session import Viewer

T = TypeVar("T")
router = APIRouter(include_in_schema=False)
api = APIRouter(tags=["robots"])


@dataclass(frozen=True)
class Console:
    """A task's page: its template and the interfaces a session may be shown (A first)."""

    template: str
    interfaces: tuple[str, ...]


CONSOLES = {
    "icreate-maze": Console("robot_icreate.html", ("video", "perception")),
    "pr2-table": Console("robot_pr2.html", ("scene",)),
}
PLAIN = Console("robot.html", ("video",))  # any other task: its camera and episode


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
    host = request.url.hostname or "127.0.0.1"
    host = f"[{host}]" if ":" in host else host
    scheme = "wss" if lab.bridge_tls else "ws"
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


def _robot(lab: Site, name: str) -> RobotLink | None:
    return next((r for r in lab.robots if r.name == name), None)


def assign(lab: Site, console: Console, asked: str | None) -> tuple[str, str]:
    """The interface a new session is shown, and how it was chosen: ``override`` (the
    page's ``?interface=``), ``random`` (drawn in the lab's ratio) or ``only``."""
    if asked:
        if asked not in console.interfaces:
            choices = " or ".join(console.interfaces)
            raise ValueError(f"interface {asked!r}: this robot's page shows {choices}")
        return asked, "override"
    if len(console.interfaces) == 1:
        return console.interfaces[0], "only"
    first, second = console.interfaces[:2]
    return (first if lab.rng.random() < lab.interface_ratio else second), "random"


@router.get("/robots", response_class=HTMLResponse)
def robots(request: Request, viewer: Viewer) -> HTMLResponse:
    lab = site(request)
    states = [state(request, lab, r) for r in lab.robots]
    context = {"robots": states, "reservations": lab.reservations}
    return page(request, "robots.html", context, user=viewer)


@router.get("/robots/{name}", response_class=HTMLResponse, name="robot_page")
def robot_page(
    request: Request, name: str, viewer: Viewer, interface: str | None = None
) -> HTMLResponse:
    lab = site(request)
    robot = _robot(lab, name)
    if robot is None:
        names = ", ".join(r.name for r in lab.robots) or "none"
        return missing(request, viewer, f"No robot {name}", f"This lab's live robots: {names}.")
    console = CONSOLES.get(robot.task, PLAIN)
    try:
        shown, assigned = assign(lab, console, interface)
    except ValueError as err:
        return page(
            request,
            "error.html",
            {
                "title": "No such interface",
                "message": str(err),
                "back": f"/robots/{name}",
                "back_text": "Open the page with an interface drawn at random",
            },
            user=viewer,
            status_code=422,
        )
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
    }
    return page(
        request,
        console.template,
        {"robot": state(request, lab, robot), "config": config, "interface": shown},
        user=viewer,
    )


@api.get("/api/robots", response_model=list[RobotState])
def robot_list(request: Request) -> list[RobotState]:
    """The live robots this lab hosts: their task, their bridge address, who drives
    each and the episode's seed."""
    lab = site(request)
    return [state(request, lab, r) for r in lab.robots]


@api.get(
    "/api/robots/{name}/scene",
    name="robot_scene",
    response_class=Response,
    responses={200: {"model": LiveScene, "description": "the model now"}, **responses(404)},
)
async def robot_scene(request: Request, name: str) -> Response:
    """The live robot's model as it is now, to draw in 3D (bodies, geoms, textures) and
    pose from its topics (``/joint_states``, ``/tf``): each episode has its own model."""
    lab = site(request)
    drive = lab.drives.get(name)
    if drive is None:
        raise ApiError(404, f"no live robot {name} here")
    scenes: Scenes = request.app.state.__dict__.setdefault("robot_scenes", Scenes())
    return Response(
        await scenes.scene(lab, drive),
        media_type="application/json",
        headers={"Cache-Control": "no-store"},
    )


async def on_robots_loop(lab: Site, work: Callable[[], T]) -> T:
    """``work()`` done on the loop the live robots step on, between two of their ticks."""
    loop = lab.robots_loop
    if loop is None or loop is asyncio.get_running_loop():
        return work()

    async def there() -> T:
        return work()

    return await asyncio.wrap_future(asyncio.run_coroutine_threadsafe(there(), loop))


@dataclass(frozen=True)
class _Snapshot:
    """A live robot's state at one tick, taken on the robots' loop (a tenth of a
    millisecond), to pose its scene elsewhere."""

    sim: Simulation  # its episode: a new one has a new model
    model: mujoco.MjModel | None  # a copy of the episode's model, when asked for
    tick: int
    seed: int
    qpos: np.ndarray
    transforms: dict[tuple[str, str], tuple[np.ndarray, np.ndarray]]


def _snapshot(drive: Driving, known: Simulation | None) -> _Snapshot:
    """The robot's state now, and a copy of its model unless its episode is ``known``
    (the model is freed when the episode ends, so it is copied here, not read later)."""
    sim = drive.robot.sim
    physics = sim.physics
    tf = sim.task.observe(physics, "/tf", {"sec": 0, "nanosec": 0}) or {"transforms": []}
    transforms = {}
    for item in tf["transforms"]:
        t, q = item["transform"]["translation"], item["transform"]["rotation"]
        transforms[(item["header"]["frame_id"], item["child_frame_id"])] = (
            np.array([t["x"], t["y"], t["z"]]),
            np.array([q["w"], q["x"], q["y"], q["z"]]),
        )
    return _Snapshot(
        sim=sim,
        model=None if sim is known else copy.copy(physics.model.ptr),
        tick=sim.tick,
        seed=sim.seed,
        qpos=np.array(physics.data.qpos),
        transforms=transforms,
    )


@dataclass
class _Episode:
    sim: Simulation
    model: mujoco.MjModel
    described: asyncio.Task[dict[str, Any]]


class Scenes:
    """Each live robot's scene for its pages, made off the robots' loop: described once
    per episode (drawing its textures takes 40-400 ms) and posed once per tick, however
    many pages ask; requests that come meanwhile wait for the one under way, and a page
    that leaves cancels nothing.

    It lives on the pages' loop and is used only there; the robots' loop only takes
    snapshots (``_snapshot``).
    """

    def __init__(self) -> None:
        self._episodes: dict[str, _Episode] = {}
        self._posed: dict[str, tuple[Simulation, int, asyncio.Task[bytes]]] = {}

    async def scene(self, lab: Site, drive: Driving) -> bytes:
        """The robot's scene now, as the JSON body of ``LiveScene``."""
        sim = drive.robot.sim  # read from this thread: which episode, and its tick
        kept = self._posed.get(drive.name)
        if kept is None or kept[0] is not sim or kept[1] != sim.tick:
            posing = asyncio.ensure_future(self._pose(lab, drive))
            kept = self._posed[drive.name] = (sim, sim.tick, posing)
            posing.add_done_callback(lambda done: self._forget_posed(drive.name, done))
        return await asyncio.shield(kept[2])

    async def _pose(self, lab: Site, drive: Driving) -> bytes:
        episode = self._episodes.get(drive.name)
        known = episode.sim if episode is not None else None
        shot = await on_robots_loop(lab, lambda: _snapshot(drive, known))
        if episode is None or episode.sim is not shot.sim:
            assert shot.model is not None
            describing = asyncio.ensure_future(asyncio.to_thread(scene.describe, shot.model))
            episode = self._episodes[drive.name] = _Episode(shot.sim, shot.model, describing)
            describing.add_done_callback(lambda done: self._forget_episode(drive.name, done))
        described = await episode.described
        return await asyncio.to_thread(_body, episode.model, described, shot)

    # A task that failed is forgotten, so the next request tries again (and the failure,
    # retrieved here, is raised to the requests that waited on it).
    def _forget_posed(self, name: str, done: asyncio.Task[bytes]) -> None:
        kept = self._posed.get(name)
        if _failed(done) and kept is not None and kept[2] is done:
            del self._posed[name]

    def _forget_episode(self, name: str, done: asyncio.Task[dict[str, Any]]) -> None:
        kept = self._episodes.get(name)
        if _failed(done) and kept is not None and kept.described is done:
            del self._episodes[name]


def _failed(task: asyncio.Task[Any]) -> bool:
    return task.cancelled() or task.exception() is not None


def _body(model: mujoco.MjModel, described: dict[str, Any], shot: _Snapshot) -> bytes:
    posed = scene.posing(model, shot.qpos, shot.transforms)
    return orjson.dumps({**described, **posed, "seed": shot.seed})
