"""Cameras: headless rendering, JPEG, camera_info, and projecting points to pixels.

Rendering goes through dm_control's ``physics.render`` on the backend that
``MUJOCO_GL`` names (``egl`` on a headless machine: Mesa's CPU rasteriser). The JPEG
encoder is libjpeg-turbo (``simplejpeg``), whose output is a function of the pixels,
so identical renders give identical bytes. Each camera keeps dm_control's ``Camera``
(its scene) for the physics it renders, rather than building one a frame as
``physics.render`` does: a live 640x480 camera's frame costs about a third less.

After each frame the GL context is released from the thread that rendered
(``labd.gl.release``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import simplejpeg
from dm_control.mujoco import engine

from labd.gl import release
from labd.sim.base import Stamp


@dataclass(frozen=True)
class Camera:
    """A camera of the model, seen as a ROS camera."""

    name: str  # the MJCF camera's name
    frame_id: str  # its optical frame in /tf (z forward, x right, y down)
    width: int = 320
    height: int = 240
    quality: int = 85
    # dm_control's camera for the physics last rendered (a task's physics is its own)
    _view: dict[str, Any] = field(default_factory=dict, init=False, compare=False, repr=False)

    def focal(self, physics: Any) -> float:
        fovy = math.radians(float(physics.named.model.cam_fovy[self.name]))
        return 0.5 * self.height / math.tan(0.5 * fovy)

    def center(self) -> tuple[float, float]:
        return (self.width - 1) / 2.0, (self.height - 1) / 2.0

    def render(self, physics: Any) -> np.ndarray:
        view = self._view
        if view.get("physics") is not physics:
            view["physics"] = physics
            view["camera"] = engine.Camera(physics, self.height, self.width, self.name)
        try:
            pixels: np.ndarray = view["camera"].render()
        finally:
            release(physics)
        return pixels

    def image(self, physics: Any, stamp: Stamp) -> dict[str, Any]:
        """sensor_msgs/msg/CompressedImage (JPEG) of what the camera sees now."""
        pixels = np.ascontiguousarray(self.render(physics))
        data = simplejpeg.encode_jpeg(pixels, quality=self.quality, colorspace="RGB")
        return {
            "header": {"stamp": stamp, "frame_id": self.frame_id},
            "format": "jpeg",
            "data": data,
        }

    def info(self, physics: Any, stamp: Stamp) -> dict[str, Any]:
        """sensor_msgs/msg/CameraInfo: a pinhole camera without distortion."""
        f = float(self.focal(physics))
        cx, cy = (float(c) for c in self.center())
        return {  # in normal form: the robot publishes it unvalidated
            "header": {"stamp": stamp, "frame_id": self.frame_id},
            "height": self.height,
            "width": self.width,
            "distortion_model": "plumb_bob",
            "d": [0.0] * 5,
            "k": [f, 0.0, cx, 0.0, f, cy, 0.0, 0.0, 1.0],
            "r": [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
            "p": [f, 0.0, cx, 0.0, 0.0, f, cy, 0.0, 0.0, 0.0, 1.0, 0.0],
            "binning_x": 0,
            "binning_y": 0,
            "roi": {"x_offset": 0, "y_offset": 0, "height": 0, "width": 0, "do_rectify": False},
        }

    def to_optical(self, physics: Any, points: np.ndarray) -> np.ndarray:
        """World points (N x 3) in the optical frame: x right, y down, z forward."""
        pos = physics.named.data.cam_xpos[self.name]
        rot = physics.named.data.cam_xmat[self.name].reshape(3, 3)
        local = (np.asarray(points, dtype=float) - pos) @ rot  # MuJoCo: x right, y up, -z ahead
        optical: np.ndarray = local * np.array([1.0, -1.0, -1.0])
        return optical

    def project(self, physics: Any, optical: np.ndarray) -> np.ndarray:
        """Pixel coordinates (N x 2, column and row) of optical-frame points with z > 0."""
        f = self.focal(physics)
        cx, cy = self.center()
        z = optical[:, 2:3]
        return np.hstack([f * optical[:, 0:1] / z + cx, f * optical[:, 1:2] / z + cy])
