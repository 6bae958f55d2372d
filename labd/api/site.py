"""The live robots as the lab's HTTP face knows them, and their 3D scenes.

``Site`` is what the pages and the API know of the lab beyond its archive: its live
robots, its bridge, who drives each robot, and the loop the robots step on (``labd.lab``
fills it in once the bridge listens). ``Scenes`` makes each live robot's scene for its
pages (``GET /api/robots/{name}/scene``) off the robots' loop.
"""

from __future__ import annotations

import asyncio
import copy
import random
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, TypeVar

import mujoco
import numpy as np
import orjson

from labd.live import Driving
from labd.recorder import scene
from labd.sim.simulation import Simulation

T = TypeVar("T")


@dataclass(frozen=True)
class RobotLink:
    """A live robot ``labd serve`` hosts, as the pages list it."""

    name: str
    task: str
    live: bool


@dataclass(frozen=True)
class Site:
    """What the pages and the API know of the lab beyond its archive: its live robots,
    its bridge."""

    robots: tuple[RobotLink, ...] = ()
    bridge_port: int | None = None
    bridge_tls: bool = False  # the bridge speaks wss://
    # Who drives each live robot, by name (``labd.live``): the robots' pages and list.
    drives: Mapping[str, Driving] = field(default_factory=dict)
    # The share of robot-page sessions shown the camera (interface A, "video"); the
    # others get the perceptual space (B). Drawn per page load with ``rng``.
    interface_ratio: float = 0.5
    rng: random.Random = field(default_factory=random.Random)
    reservations: bool = False  # live robots are driven only with a reservation's key
    # The loop the live robots step on, when the pages run on another (``labd.lab``):
    # what touches a robot is done there, between two ticks. None: the pages' own.
    robots_loop: asyncio.AbstractEventLoop | None = None


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
