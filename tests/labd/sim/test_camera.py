"""Cameras and threads: a simulation may render on one thread and be freed on another."""

from __future__ import annotations

import gc
import sys
import threading
from typing import Any

import numpy as np
import pytest

from labd.sim.simulation import Simulation
from labd.video import Video, VideoSpec


@pytest.fixture
def unraisable(monkeypatch: pytest.MonkeyPatch) -> list[Any]:
    """What ``__del__`` methods raise meanwhile (the garbage collector only reports it)."""
    said: list[Any] = []
    monkeypatch.setattr(sys, "unraisablehook", said.append)
    return said


def on_a_thread(fn: Any) -> Any:
    done: list[Any] = []
    thread = threading.Thread(target=lambda: done.append(fn()))
    thread.start()
    thread.join()
    assert done, "the thread failed"
    return done[0]


def test_a_simulation_rendered_on_another_thread_is_freed_here(unraisable):
    """A simulation whose camera rendered on a thread now gone, and that nobody closed, is
    freed by the garbage collector on this thread without an EGL error; meanwhile it
    still renders here, the same pixels."""
    sims: list[Simulation] = []

    def render() -> np.ndarray:
        sim = Simulation("icreate-maze", seed=1)
        sims.append(sim)
        return sim.task.camera.render(sim.physics)

    there = on_a_thread(render)
    here = sims[0].task.camera.render(sims[0].physics)
    assert np.array_equal(there, here)
    on_a_thread(lambda: sims[0].task.camera.render(sims[0].physics))  # and back again
    sims.clear()
    gc.collect()
    assert [str(u.exc_value) for u in unraisable] == []


@pytest.mark.parametrize("camera", ["front", "scene"])
def test_a_video_rendered_on_another_thread_is_freed_here(unraisable, tmp_path, camera):
    """The same for the physics a video was rendered from (a replay on a worker thread),
    from the model's camera or the view of the whole scene."""
    kept: list[Any] = []

    def record() -> int:
        sim = Simulation("icreate-maze", seed=1)
        video = Video(VideoSpec(camera), tmp_path / "video.mp4")
        kept.append((sim, video))
        video(sim.physics, 0)
        video.close()
        return video.frames

    assert on_a_thread(record) == 1
    kept.clear()
    gc.collect()
    assert [str(u.exc_value) for u in unraisable] == []
