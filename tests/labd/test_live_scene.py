"""A live robot's 3D scene for its pages: described once per episode and posed once per
tick, however many pages ask at once, with the robot's state read on the robots' loop."""

from __future__ import annotations

import asyncio
import threading

import orjson
import pytest

from labd.api.site import RobotLink, Scenes, Site
from labd.graph.types import TypeRegistry
from labd.live import Driving
from labd.recorder import scene
from labd.station import Station


@pytest.fixture
def drive(tmp_path):
    station = Station(TypeRegistry.default(), "pr2-1", "pr2-table", {}, 0, live=True,
                      protected_prefixes=())  # fmt: skip
    driving = Driving(station, work=None)
    yield driving
    driving.close()
    station.close()


@pytest.fixture
def robots_loop():
    """The loop the robot steps on, on a thread of its own as in ``labd serve``."""
    loop = asyncio.new_event_loop()
    thread = threading.Thread(target=loop.run_forever, name="robots", daemon=True)
    thread.start()
    yield loop
    loop.call_soon_threadsafe(loop.stop)
    thread.join(10)
    loop.close()


@pytest.fixture
def described(monkeypatch):
    """Each description of a model, counted."""
    made = []
    describe = scene.describe

    def counted(model):
        made.append(threading.current_thread().name)
        return describe(model)

    monkeypatch.setattr(scene, "describe", counted)
    return made


async def test_a_crowd_of_pages_describes_the_scene_once_per_episode(drive, robots_loop, described):
    """Fifty requests at once: one description, off the robots' loop, and one body for
    the tick; after a reset (on the robots' loop), one new description for the new model."""
    site = Site((RobotLink("pr2-1", "pr2-table", True),), drives={"pr2-1": drive},
                robots_loop=robots_loop)  # fmt: skip
    scenes = Scenes()
    bodies = await asyncio.gather(*(scenes.scene(site, drive) for _ in range(50)))
    assert len(described) == 1 and described[0] != "robots"
    assert all(body is bodies[0] for body in bodies)  # one posing for the tick
    first = orjson.loads(bodies[0])
    assert first["seed"] == 0 and first["bodies"] and first["joints"]

    done = asyncio.run_coroutine_threadsafe(_reset(drive), robots_loop)
    await asyncio.wrap_future(done)
    again = await asyncio.gather(*(scenes.scene(site, drive) for _ in range(50)))
    assert len(described) == 2
    assert orjson.loads(again[0])["seed"] == 1


async def _reset(drive: Driving) -> None:
    drive.robot.reset()


async def test_a_failed_description_is_tried_again(drive, monkeypatch):
    """A description that fails fails the requests that waited on it, not the next one."""
    site = Site((RobotLink("pr2-1", "pr2-table", True),), drives={"pr2-1": drive})
    describe = scene.describe
    monkeypatch.setattr(scene, "describe", lambda model: 1 / 0)
    scenes = Scenes()
    with pytest.raises(ZeroDivisionError):
        await scenes.scene(site, drive)
    monkeypatch.setattr(scene, "describe", describe)
    assert orjson.loads(await scenes.scene(site, drive))["seed"] == 0
