"""Videos of a trial rendered after the fact, during its replay (``labd.replay``).

Any camera of the task can be rendered, whether or not the controller ever looked
through it, and so can a third-person view of the whole scene (``scene``: a free camera
looking at the model from above and aside). Frames are rendered from the replayed
physics at the chosen rate and encoded as H.264 MP4 with PyAV (FFmpeg in the wheel),
which browsers play and LeRobot reads. A video is a derived artifact: it never changes
the record or its digests.
"""

from __future__ import annotations

from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path
from typing import Any

import av
import numpy as np
from dm_control.mujoco.engine import MovableCamera

from labd.errors import LabError
from labd.gl import release

SCENE = "scene"  # the third-person view
FIRST = ""  # the model's first camera, whatever its name (a worker's video of any task)


class VideoError(LabError):
    """A video that cannot be made: an unknown camera, a bad size or rate."""


@dataclass(frozen=True)
class VideoSpec:
    camera: str  # a camera of the model, or "scene"
    width: int = 320
    height: int = 240
    fps: float = 10.0

    @classmethod
    def parse(cls, camera: str, size: str = "320x240", fps: float = 10.0) -> VideoSpec:
        try:
            width, height = (int(n) for n in size.lower().split("x"))
        except ValueError:
            raise VideoError(f"size {size!r}: write WIDTHxHEIGHT, e.g. 640x480") from None
        if not (16 <= width <= 3840 and 16 <= height <= 2160) or width % 2 or height % 2:
            raise VideoError(f"size {size}: even numbers from 16x16 to 3840x2160")
        if not 0.1 <= fps <= 120:
            raise VideoError(f"fps {fps:g}: from 0.1 to 120")
        return cls(camera, width, height, fps)


class Video:
    """Renders frames of one camera from the replayed physics into an MP4 file.

    Called after every tick with the physics and the tick number; a frame is rendered
    whenever the simulation time reaches the next frame's time.
    """

    def __init__(self, spec: VideoSpec, out: Path) -> None:
        self.spec = spec
        self.out = out
        self.period = 1.0 / spec.fps
        self.frames = 0
        self.camera = spec.camera  # the camera rendered (FIRST's, once known)
        self._next = 0.0
        self._container: Any = None
        self._stream: Any = None
        self._scene: MovableCamera | None = None

    def _open(self) -> None:
        self.out.parent.mkdir(parents=True, exist_ok=True)
        self._container = av.open(str(self.out), mode="w", format="mp4")
        rate = Fraction(self.spec.fps).limit_denominator(1000)
        self._stream = self._container.add_stream("libx264", rate=rate)
        self._stream.width = self.spec.width
        self._stream.height = self.spec.height
        self._stream.pix_fmt = "yuv420p"
        self._stream.options = {"crf": "23", "preset": "veryfast", "threads": "1"}

    def __call__(self, physics: Any, tick: int) -> None:
        time = float(physics.data.time)
        if time + 1e-9 < self._next:
            return
        self._next += self.period
        try:
            pixels = self._render(physics)  # an unknown camera fails here, before any file
        finally:
            release(physics)  # its GL context may be freed on another thread
        if self._container is None:
            self._open()
        frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(pixels), format="rgb24")
        for packet in self._stream.encode(frame):
            self._container.mux(packet)
        self.frames += 1

    def _render(self, physics: Any) -> np.ndarray:
        spec = self.spec
        if spec.camera == SCENE:
            if self._scene is None:
                self._scene = MovableCamera(physics, spec.height, spec.width)
                stat = physics.model.stat
                self._scene.set_pose(
                    lookat=np.array(stat.center), distance=1.6 * float(stat.extent),
                    azimuth=90.0, elevation=-55.0,
                )  # fmt: skip
            pixels: np.ndarray = self._scene.render()
            return pixels
        names = [physics.model.id2name(i, "camera") for i in range(physics.model.ncam)]
        if spec.camera == FIRST and names:
            self.camera = names[0]
            rendered_first: np.ndarray = physics.render(spec.height, spec.width, camera_id=0)
            return rendered_first
        if spec.camera not in names:
            raise VideoError(
                f"the task has no camera {spec.camera!r}; its cameras are"
                f" {', '.join(names) or 'none'}, and {SCENE!r} is a view of the whole scene"
            )
        rendered: np.ndarray = physics.render(spec.height, spec.width, camera_id=spec.camera)
        return rendered

    def close(self) -> None:
        if self._container is None:
            return
        for packet in self._stream.encode():
            self._container.mux(packet)
        self._container.close()
        self._container = None
