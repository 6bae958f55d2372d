"""Fiducial tags on the maze walls: their patterns, placement, and what the camera sees.

A tag looks like an AprilTag: a black square with a 6 x 6 grid of bits inside a
one-cell black border, on a white plate one cell wider all round (10 x 10 cells).
The bits come from the id through SHA-256, so the same id always looks the same;
they are not a real AprilTag family and nothing decodes them: ``/ar_tags`` reports
tags from the geometry, as a perfect detector would, which makes it cheap enough
to publish every tick and exact enough to test against.

A tag's frame follows the AprilTag 3 convention: origin at the centre of the black
square, x to the right and y down as seen by someone facing the tag, z into the
wall. A camera looking straight at a tag sees it with the identity rotation.

A tag is reported when its printed side faces the camera within ``MAX_VIEW_ANGLE``,
its four corners lie inside the image, it spans at least ``MIN_PIXELS`` both ways,
and rays from the camera to its centre and to points just inside its corners reach
it without meeting a wall.
"""

from __future__ import annotations

import hashlib
import io
import math
from dataclasses import dataclass
from typing import Any

import mujoco
import numpy as np
from PIL import Image

from labd.sim.camera import Camera
from labd.sim.icreate.layout import DIRECTIONS, Layout

TAG_SIZE = 0.16  # metres: the black square's side, which the detector measures
PLATE = TAG_SIZE * 10 / 8  # the white plate around it
TAG_HEIGHT = 0.2  # metres: the centre above the floor, the camera's height
STANDOFF = 0.001  # metres in front of the wall, so the plate is never inside it
ID_RANGE = 587  # ids are drawn from 0..586, as many as the tag36h11 family holds
MAX_VIEW_ANGLE = math.radians(70)  # from the tag's normal; beyond it, too oblique to read
MIN_PIXELS = 10.0  # a detector needs the tag this many pixels wide and high
CORNER_INSET = 0.9  # occlusion rays aim this far from the centre toward each corner
TEXTURE_SCALE = 8  # texture pixels per pattern cell
_MUJOCO_TO_OPTICAL = np.array([1.0, -1.0, -1.0])
_MAZE_ONLY = np.array([1, 0, 0, 0, 0, 0], dtype=np.uint8)  # rays meet walls, nothing else


@dataclass(frozen=True, eq=False)  # numpy fields: compare tags by id
class Tag:
    """One tag: its id and where it hangs, in the world frame."""

    id: int
    centre: np.ndarray  # (3,)
    rotation: np.ndarray  # (3, 3): the tag frame's axes as columns
    corners: np.ndarray  # (4, 3): top-left, top-right, bottom-right, bottom-left

    @property
    def normal(self) -> np.ndarray:
        """Out of the printed side, away from the wall."""
        out: np.ndarray = -self.rotation[:, 2]
        return out


def place(layout: Layout, count: int, rng: np.random.Generator) -> list[Tag]:
    """``count`` tags (fewer if the maze has fewer wall faces) with distinct ids."""
    faces = layout.faces()
    count = min(count, len(faces))
    chosen = sorted(rng.choice(len(faces), size=count, replace=False).tolist())
    ids = rng.choice(ID_RANGE, size=count, replace=False).tolist()
    tags = []
    for index, tag_id in zip(chosen, ids, strict=True):
        face = faces[index]
        nx, ny = DIRECTIONS[face.normal]
        normal = np.array([nx, ny, 0.0])
        up = np.array([0.0, 0.0, 1.0])
        right = np.cross(up, normal)
        centre = np.array([face.x, face.y, TAG_HEIGHT]) + STANDOFF * normal
        half = TAG_SIZE / 2
        corners = np.array([centre + half * (sx * right + sy * up) for sx, sy in _CORNER_SIGNS])
        rotation = np.column_stack([right, -up, -normal])
        tags.append(Tag(int(tag_id), centre, rotation, corners))
    return tags


_CORNER_SIGNS = ((-1, 1), (1, 1), (1, -1), (-1, -1))


def pattern(tag_id: int) -> np.ndarray:
    """The tag's 10 x 10 cells, True for black: white margin, black border, 6 x 6 bits."""
    digest = int.from_bytes(hashlib.sha256(f"labd-tag:{tag_id}".encode()).digest()[:8], "big")
    bits = np.array([(digest >> k) & 1 for k in range(36)], dtype=bool).reshape(6, 6)
    cells = np.zeros((10, 10), dtype=bool)
    cells[1:9, 1:9] = True
    cells[2:8, 2:8] = bits
    return cells


def texture_png(tag_id: int) -> bytes:
    """The tag's pattern as a PNG, ``TEXTURE_SCALE`` pixels per cell."""
    cells = np.kron(pattern(tag_id), np.ones((TEXTURE_SCALE, TEXTURE_SCALE), dtype=bool))
    pixels = np.where(cells, 0, 255).astype(np.uint8)
    out = io.BytesIO()
    Image.fromarray(np.stack([pixels] * 3, axis=-1)).save(out, format="PNG")
    return out.getvalue()


def tag_xml(tag: Tag) -> tuple[str, str, dict[str, bytes]]:
    """The tag's asset lines, its geom (a plate, seen but never colliding) and its files."""
    name = f"tag{tag.id}"
    asset = f"""
    <texture name="{name}" type="2d" file="{name}.png"/>
    <material name="{name}" texture="{name}" texrepeat="1 1"/>"""
    right, up = tag.rotation[:, 0], -tag.rotation[:, 1]
    axes = " ".join(f"{v:g}" for v in (*right, *up))
    x, y, z = tag.centre
    geom = f"""
    <geom name="{name}" type="plane" pos="{x:g} {y:g} {z:g}" xyaxes="{axes}"
          size="{PLATE / 2:g} {PLATE / 2:g} {PLATE / 2:g}" contype="0" conaffinity="0"
          group="2" material="{name}"/>"""
    return asset, geom, {f"{name}.png": texture_png(tag.id)}


class Detector:
    """Finds the tags a camera sees, from the geometry (see the module's docstring)."""

    def __init__(self, tags: list[Tag], camera: Camera) -> None:
        self.tags = sorted(tags, key=lambda t: t.id)  # so detections come out by id
        self.camera = camera
        centres = np.array([t.centre for t in self.tags]).reshape(-1, 3)
        corners = np.array([t.corners for t in self.tags]).reshape(-1, 4, 3)
        self.normals = np.array([t.normal for t in self.tags]).reshape(-1, 3)
        self.offsets = np.einsum("ij,ij->i", centres, self.normals)  # each tag's plane
        # The centre and corners of every tag, one row each, in tag order.
        self.points = np.concatenate([centres[:, None], corners], axis=1).reshape(-1, 3)
        # Where the occlusion rays aim: the centre and points just inside the corners.
        inset = centres[:, None] + CORNER_INSET * (corners - centres[:, None])
        self.targets = np.concatenate([centres[:, None], inset], axis=1)

    def detect(self, physics: Any) -> list[dict[str, Any]]:
        """lab_msgs/msg/ArTag values for every tag seen now, by increasing id.

        Runs every tick: a few array operations put every tag's centre and corners
        in the optical frame, then a plain loop applies the tests (there are few
        tags, and most fail the first test). The optical frame and pinhole model are
        ``Camera``'s.
        """
        if not self.tags:
            return []
        camera = self.camera
        cam = physics.model.camera(camera.name).id
        eye = physics.data.cam_xpos[cam].copy()
        # World to optical frame: MuJoCo's camera axes (x right, y up, -z ahead) flipped.
        frame = physics.data.cam_xmat[cam].reshape(3, 3) * _MUJOCO_TO_OPTICAL
        heights = (self.normals @ eye - self.offsets).tolist()  # the eye above each plane
        optical = ((self.points - eye) @ frame).tolist()
        f = camera.focal(physics)
        cx, cy = camera.center()
        right, bottom = camera.width - 1, camera.height - 1
        cos_limit = math.cos(MAX_VIEW_ANGLE)
        seen = []
        for k, height in enumerate(heights):
            x, y, z = optical[5 * k]
            distance = math.sqrt(x * x + y * y + z * z)
            if height <= distance * cos_limit:  # its back, or too oblique
                continue
            corners = optical[5 * k + 1 : 5 * k + 5]
            if min(c[2] for c in corners) <= 0.01:
                continue
            us = [f * c[0] / c[2] + cx for c in corners]
            vs = [f * c[1] / c[2] + cy for c in corners]
            low_u, high_u, low_v, high_v = min(us), max(us), min(vs), max(vs)
            if low_u < 0 or low_v < 0 or high_u > right or high_v > bottom:
                continue
            if high_u - low_u < MIN_PIXELS or high_v - low_v < MIN_PIXELS:
                continue
            box = (f * x / z + cx, f * y / z + cy, high_u - low_u, high_v - low_v)
            seen.append((k, (x, y, z), distance, box))
        if not seen:
            return []
        clear = self._unoccluded(physics, eye, np.array([k for k, *_ in seen]))
        out = []
        quat = np.zeros(4)
        for (k, (x, y, z), distance, (u, v, width, height)), visible in zip(
            seen, clear.tolist(), strict=True
        ):
            if not visible:
                continue
            mujoco.mju_mat2Quat(quat, (frame.T @ self.tags[k].rotation).ravel())
            w, qx, qy, qz = quat.tolist()
            out.append(
                {
                    "id": self.tags[k].id,
                    "cx": u,
                    "cy": v,
                    "width": width,
                    "height": height,
                    "size": TAG_SIZE,
                    "distance": distance,
                    "pose": {
                        "position": {"x": x, "y": y, "z": z},
                        "orientation": {"x": qx, "y": qy, "z": qz, "w": w},
                    },
                }
            )
        return out

    def _unoccluded(self, physics: Any, eye: np.ndarray, tags: np.ndarray) -> np.ndarray:
        """For each of ``tags``: whether rays from ``eye`` to its centre and corners meet
        no wall before they reach it."""
        rays = (self.targets[tags] - eye).reshape(-1, 3)
        lengths = np.sqrt(np.einsum("ij,ij->i", rays, rays))
        directions = np.ascontiguousarray(rays / lengths[:, None]).ravel()
        count = len(lengths)
        geoms = np.zeros(count, dtype=np.int32)
        hits = np.zeros(count)
        mujoco.mj_multiRay(
            physics.model.ptr,
            physics.data.ptr,
            eye,
            directions,
            _MAZE_ONLY,
            1,
            -1,
            geoms,
            hits,
            None,
            count,
            float(lengths.max()) + 1.0,
        )
        blocked = (hits >= 0) & (hits < lengths - STANDOFF / 2)
        clear: np.ndarray = ~blocked.reshape(-1, 5).any(axis=1)
        return clear
