"""The scene of a record: its task's model, and the robot's state at each tick.

A record carries the compiled model of its task (the attachment ``model.xml``, with
the textures it names under ``model/``), so the scene is rebuilt from the record
alone, for any task, with MuJoCo's own compiler:

- ``describe``: the bodies (parent, pose at rest, joints) and the visible geoms
  (shape, size, colour, and 2D textures as PNG) that a page needs to draw the scene
  and pose it at any tick by forward kinematics, as MuJoCo does;
- ``Poser``: the model's joint positions (``qpos``) from what the record says:
  ``/joint_states`` by joint name, ``/tf`` from ``odom`` to a body of the model (a
  free body, or one on planar joints, as the maze robot and the PR2's base are), and
  detected objects (``/objects``) for the free bodies named like them. What the
  record never says (an object the camera never saw) stays where the model put it;
- ``floor_map``: a top-down map in the ``odom`` frame when the model has walls (the
  maze's ``wall*`` boxes, ``tag<id>`` plates and its ``goal`` mark);
- ``posing``: for a live robot, what a page needs beside ``describe`` to pose the
  scene from the robot's topics as ``Poser`` does (the live PR2 page, ``live/pr2.js``).

The ``odom`` frame is where the robot's root body was at the start: its pose in the
world is the body's pose at rest, composed with the first ``/tf`` from ``odom``.
"""

from __future__ import annotations

import base64
import io
import math
import re
from collections.abc import Mapping
from typing import Any

import mujoco
import numpy as np
from PIL import Image

from labd.errors import SummaryError
from repository.well_known import MODEL, MODEL_ASSETS

FREE, BALL, SLIDE, HINGE = 0, 1, 2, 3  # mjtJoint
SHAPES = {0: "plane", 2: "sphere", 3: "capsule", 4: "ellipsoid", 5: "cylinder", 6: "box"}
VISIBLE_GROUPS = (0, 1, 2)  # MuJoCo's viewer shows these by default
PLANE_EXTENT = 5.0  # metres either way of an infinite plane
TAG = re.compile(r"tag(\d+)$")
Pose = tuple[np.ndarray, np.ndarray]  # position (3,), quaternion w, x, y, z (4,)


def load(attachments: Mapping[str, bytes]) -> mujoco.MjModel | None:
    """The record's model, compiled; None if the record carries none."""
    xml = attachments.get(MODEL)
    if xml is None:
        return None
    assets = {
        k[len(MODEL_ASSETS) :]: v for k, v in attachments.items() if k.startswith(MODEL_ASSETS)
    }
    try:
        return mujoco.MjModel.from_xml_string(xml.decode(), assets)
    except (ValueError, UnicodeDecodeError) as err:
        raise SummaryError(f"the record's {MODEL} does not compile: {err}") from None


def describe(model: mujoco.MjModel) -> dict[str, Any]:
    """Bodies, visible geoms and their textures: what a page draws (see ``record.js``)."""
    bodies = []
    for b in range(1, model.nbody):
        joints = []
        for j in range(model.body_jntadr[b], model.body_jntadr[b] + model.body_jntnum[b]):
            kind = int(model.jnt_type[j])
            adr = int(model.jnt_qposadr[j])
            ref = float(model.qpos0[adr]) if kind in (SLIDE, HINGE) else 0.0
            joints.append([kind, adr, *_r(model.jnt_axis[j]), *_r(model.jnt_pos[j]), round(ref, 6)])
        bodies.append(
            {
                "name": model.body(b).name,
                "parent": int(model.body_parentid[b]) - 1,  # -1: the world
                "pos": _r(model.body_pos[b]),
                "quat": _xyzw(model.body_quat[b]),
                "joints": joints,
            }
        )
    geoms = []
    textures: dict[int, int] = {}  # MuJoCo texture id -> index in the list below
    texture_data: list[str] = []
    for g in range(model.ngeom):
        shape = SHAPES.get(int(model.geom_type[g]))
        if shape is None or int(model.geom_group[g]) not in VISIBLE_GROUPS:
            continue
        rgba, texture, repeat = _look(model, g)
        if rgba[3] <= 0 or (shape == "plane" and _faces_down(model, g)):
            continue
        size = [float(s) for s in model.geom_size[g]]
        if shape == "plane":
            size = [s if s > 0 else PLANE_EXTENT for s in size[:2]]
        geom: dict[str, Any] = {
            "body": int(model.geom_bodyid[g]) - 1,
            "shape": shape,
            "size": _r(size),
            "pos": _r(model.geom_pos[g]),
            "quat": _xyzw(model.geom_quat[g]),
            "rgba": [round(float(c), 3) for c in rgba],
        }
        if texture is not None:
            if texture not in textures:
                textures[texture] = len(texture_data)
                texture_data.append(_png(model, texture))
            geom["texture"] = textures[texture]
            geom["repeat"] = _r(repeat)
        geoms.append(geom)
    return {"bodies": bodies, "geoms": geoms, "textures": texture_data}


def posing(
    model: mujoco.MjModel, qpos: np.ndarray, transforms: Mapping[tuple[str, str], Pose]
) -> dict[str, Any]:
    """What a page needs, beside ``describe``, to pose a live robot's scene from its topics:

    - ``qpos``: the joint positions now (objects included), where a page starts;
    - ``rest``: the model's own (``qpos0``), where ``Poser`` measures planar joints from;
    - ``joints``: the qpos address of each hinge and slide joint, by name (``/joint_states``);
    - ``root``, ``odom``: the body that ``/tf`` places from ``odom``, and where ``odom``
      is in the world (x, y, z and the quaternion x, y, z, w), from ``transforms`` now
      (parent and child frame -> pose) and the body's pose at ``qpos``.
    """
    data = mujoco.MjData(model)
    data.qpos[:] = qpos
    mujoco.mj_kinematics(model, data)
    root, odom = "", _identity()
    for (parent, child), pose in transforms.items():
        body = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, child)
        if parent == "odom" and body > 0:
            root = child
            odom = _compose((data.xpos[body].copy(), data.xquat[body].copy()), _inverse(pose))
            break
    return {
        "qpos": _r(qpos, 6),
        "rest": _r(model.qpos0, 6),
        "joints": {
            model.joint(j).name: int(model.jnt_qposadr[j])
            for j in range(model.njnt)
            if int(model.jnt_type[j]) in (SLIDE, HINGE)
        },
        "root": root,
        "odom": [*_r(odom[0], 6), *_xyzw(odom[1])],
    }


def _look(model: mujoco.MjModel, g: int) -> tuple[list[float], int | None, list[float]]:
    """A geom's colour, its 2D texture (if any), and how often it repeats across it."""
    mat = int(model.geom_matid[g])
    if mat < 0:
        return [float(c) for c in model.geom_rgba[g]], None, [1.0, 1.0]
    rgba = [float(c) for c in model.mat_rgba[mat]]
    tex = int(model.mat_texid[mat][int(mujoco.mjtTextureRole.mjTEXROLE_RGB)])
    if tex < 0 or int(model.tex_type[tex]) != int(mujoco.mjtTexture.mjTEXTURE_2D):
        return rgba, None, [1.0, 1.0]
    repeat = [float(r) for r in model.mat_texrepeat[mat]]
    if model.mat_texuniform[mat]:  # repeats per metre: so many across the geom
        size = model.geom_size[g]
        repeat = [repeat[0] * 2 * float(size[0]), repeat[1] * 2 * float(size[1])]
    return rgba, tex, repeat


def _faces_down(model: mujoco.MjModel, g: int) -> bool:
    """A plane seen from below only (the maze's sky): nothing to draw from above."""
    _, x, y, _ = (float(v) for v in model.geom_quat[g])
    return 1 - 2 * (x * x + y * y) < 0  # the plane's z axis points down


def _png(model: mujoco.MjModel, tex: int) -> str:
    """A compiled texture as a PNG data URL."""
    h, w, channels = (
        int(model.tex_height[tex]),
        int(model.tex_width[tex]),
        int(model.tex_nchannel[tex]),
    )
    start = int(model.tex_adr[tex])
    pixels = np.asarray(model.tex_data[start : start + h * w * channels], dtype=np.uint8)
    mode = {1: "L", 3: "RGB", 4: "RGBA"}[channels]
    image = Image.fromarray(pixels.reshape(h, w, channels).squeeze(), mode)
    out = io.BytesIO()
    image.save(out, format="PNG", optimize=True)
    return "data:image/png;base64," + base64.b64encode(out.getvalue()).decode()


class Poser:
    """The model's joint positions as the record tells them, message by message."""

    def __init__(self, model: mujoco.MjModel) -> None:
        self.model = model
        self.qpos = model.qpos0.copy()
        self.joints = {model.joint(j).name: j for j in range(model.njnt)}
        self.bodies = {model.body(b).name: b for b in range(1, model.nbody)}
        data = mujoco.MjData(model)
        mujoco.mj_kinematics(model, data)
        self.rest: dict[int, Pose] = {
            b: (data.xpos[b].copy(), data.xquat[b].copy()) for b in range(model.nbody)
        }
        self.world_from_odom: Pose | None = None
        self.in_odom: dict[str, Pose] = {"odom": _identity()}  # frames seen from odom

    def joint_states(self, message: Any) -> None:
        for name, value in zip(message.name, message.position, strict=False):
            j = self.joints.get(str(name))
            if j is not None and int(self.model.jnt_type[j]) in (SLIDE, HINGE):
                self.qpos[self.model.jnt_qposadr[j]] = float(value)

    def tf(self, message: Any) -> None:
        for item in message.transforms:
            parent, child = str(item.header.frame_id), str(item.child_frame_id)
            if parent not in self.in_odom:
                continue
            t, q = item.transform.translation, item.transform.rotation
            local = (np.array([t.x, t.y, t.z]), np.array([q.w, q.x, q.y, q.z]))
            pose = _compose(self.in_odom[parent], local)
            self.in_odom[child] = pose
            body = self.bodies.get(child)
            if body is None or parent != "odom":
                continue
            if self.world_from_odom is None:  # the robot's root was here at the start
                self.world_from_odom = _compose(self.rest[body], _inverse(pose))
            self._place(body, _compose(self.world_from_odom, pose))

    def objects(self, message: Any) -> None:
        """Detected objects (``lab_msgs/msg/DetectedObjectArray``) on free bodies."""
        frame = self.in_odom.get(str(message.header.frame_id))
        if frame is None or self.world_from_odom is None:
            return
        for item in message.objects:
            body = self.bodies.get(str(item.name))
            if body is None:
                continue
            p, q = item.pose.position, item.pose.orientation
            local = (np.array([p.x, p.y, p.z]), np.array([q.w, q.x, q.y, q.z]))
            self._place(body, _compose(self.world_from_odom, _compose(frame, local)))

    def _place(self, body: int, pose: Pose) -> None:
        """Set the joints of ``body`` so that it is at ``pose`` in the world."""
        m = self.model
        first, count = int(m.body_jntadr[body]), int(m.body_jntnum[body])
        kinds = [int(m.jnt_type[j]) for j in range(first, first + count)]
        position, quat = pose
        if kinds == [FREE]:
            adr = int(m.jnt_qposadr[first])
            self.qpos[adr : adr + 3] = position
            self.qpos[adr + 3 : adr + 7] = quat / np.linalg.norm(quat)
            return
        if sorted(kinds) != [SLIDE, SLIDE, HINGE]:
            return  # a body moved some other way: its joints come from /joint_states
        rest_position, rest_quat = self.rest[body]
        turn = _yaw(quat) - _yaw(rest_quat)
        for j in range(first, first + count):
            axis = m.jnt_axis[j]
            adr = int(m.jnt_qposadr[j])
            if int(m.jnt_type[j]) == HINGE:
                self.qpos[adr] = math.remainder(turn, math.tau) * float(np.sign(axis[2]) or 1)
            else:
                self.qpos[adr] = float(np.dot(position - rest_position, axis))


def floor_map(model: mujoco.MjModel, world_from_odom: Pose | None) -> dict[str, Any] | None:
    """Walls, tags and the goal seen from above, in ``odom``; None without walls."""
    odom_from_world = _inverse(world_from_odom or _identity())
    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)
    walls, tags, goal = [], [], None
    for g in range(model.ngeom):
        name = model.geom(g).name
        if int(model.geom_bodyid[g]) != 0:
            continue
        centre = _apply(odom_from_world, data.geom_xpos[g])
        axes = _rotation(odom_from_world[1]) @ data.geom_xmat[g].reshape(3, 3)
        if name.startswith("wall") or name == "goal":
            half = np.abs(axes[:2, :2]) @ model.geom_size[g][:2]
            box = _r(
                [centre[0] - half[0], centre[1] - half[1], centre[0] + half[0], centre[1] + half[1]]
            )
            if name == "goal":
                goal = box
            else:
                walls.append(box)
        elif (found := TAG.match(name)) is not None:
            normal = axes[:, 2]
            tags.append([int(found.group(1)), *_r(centre[:2]), *_r(normal[:2])])
    if not walls:
        return None
    return {"frame": "odom", "walls": walls, "tags": tags, "goal": goal}


# -- poses: (position, quaternion w x y z) -----------------------------------------------


def _identity() -> Pose:
    return np.zeros(3), np.array([1.0, 0.0, 0.0, 0.0])


def _rotation(q: np.ndarray) -> np.ndarray:
    out = np.zeros(9)
    mujoco.mju_quat2Mat(out, np.asarray(q, dtype=np.float64))
    return out.reshape(3, 3)


def _compose(a: Pose, b: Pose) -> Pose:
    quat = np.zeros(4)
    mujoco.mju_mulQuat(quat, a[1], b[1])
    return a[0] + _rotation(a[1]) @ b[0], quat


def _inverse(a: Pose) -> Pose:
    quat = np.array([a[1][0], -a[1][1], -a[1][2], -a[1][3]])
    return -(_rotation(quat) @ a[0]), quat


def _apply(a: Pose, point: np.ndarray) -> np.ndarray:
    result: np.ndarray = a[0] + _rotation(a[1]) @ point
    return result


def _yaw(q: np.ndarray) -> float:
    w, x, y, z = (float(v) for v in q)
    return math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))


def _r(values: Any, digits: int = 4) -> list[float]:
    return [round(float(v), digits) for v in values]


def _xyzw(q: Any) -> list[float]:
    """A MuJoCo quaternion (w, x, y, z) in three.js's order (x, y, z, w)."""
    w, x, y, z = (round(float(v), 6) for v in q)
    return [x, y, z, w]
