"""The messages pr2-table publishes, built from the physics in normal form.

- ``/joint_states``: every servoed joint, each gripper's gap and its two fingers;
- ``/tf``: odom -> base_footprint, and from base_footprint the frames a controller
  needs (torso_lift_link, the head camera's optical frame, both tool frames);
- ``/objects``: what the head camera sees, as a perception pipeline would report it
  (from geometry: in the image and not hidden behind something, checked by rays);
- ``/task/goal``: which object goes where.
"""

from __future__ import annotations

from typing import Any

import mujoco
import numpy as np

from labd.sim.base import Stamp
from labd.sim.camera import Camera
from labd.sim.pr2 import model, scene
from labd.sim.pr2.physics import BASE, ODOM, OPTICAL, SERVOED, TOOLS, TORSO, Physics

# /joint_states names: SERVOED, then per gripper its gap and its two fingers.
JOINT_NAMES = (
    *(j.name for j in SERVOED),
    *(
        name
        for side in model.SIDES
        for name in (
            model.GRIPPER[side].name,
            f"{side}_gripper_l_finger_joint",
            f"{side}_gripper_r_finger_joint",
        )
    ),
)
TF_CHILDREN = (TORSO, OPTICAL, TOOLS["l"], TOOLS["r"])  # each a child of base_footprint
RAY_GROUPS = np.array([1, 1, 0, 0, 0, 0], dtype=np.uint8)  # world and robot geoms block sight
NEAREST = 0.05  # m: closer to the lens than this is not seen
# Where rays aim on an object, as fractions of its half extents: its centre and corners
# a little inside, so that an object is seen unless every one of them is hidden.
_CORNERS = np.array(
    [(0.0, 0.0, 0.0)] + [(x, y, z) for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]
)


def quaternion(rotation: np.ndarray) -> dict[str, float]:
    """A rotation matrix as a geometry_msgs/Quaternion (x, y, z, w)."""
    quat = np.zeros(4)
    mujoco.mju_mat2Quat(quat, np.ascontiguousarray(rotation).reshape(9))
    if quat[0] < 0:  # one of the two equal quaternions, always the same one
        quat = -quat
    w, x, y, z = (float(v) for v in quat)
    return {"x": x, "y": y, "z": z, "w": w}


def relative(
    parent: tuple[np.ndarray, np.ndarray], child: tuple[np.ndarray, np.ndarray]
) -> tuple[np.ndarray, np.ndarray]:
    """``child``'s pose in ``parent``'s frame (both given in the same frame)."""
    position = parent[1].T @ (child[0] - parent[0])
    return position, parent[1].T @ child[1]


def _vector(v: np.ndarray) -> dict[str, float]:
    return {"x": float(v[0]), "y": float(v[1]), "z": float(v[2])}


def joint_state(physics: Physics, stamp: Stamp) -> dict[str, Any]:
    """sensor_msgs/JointState: positions (rad, m), velocities, efforts (N m, N)."""
    fingers = physics.finger_positions()
    finger_speeds = physics.finger_velocities()
    finger_forces = physics.finger_forces()
    position = physics.servo_positions().tolist()
    velocity = physics.servo_velocities().tolist()
    effort = physics.servo_efforts().tolist()
    for i in (0, 2):  # a gripper: the gap (sum of the fingers), then each finger
        position += [float(fingers[i] + fingers[i + 1]), float(fingers[i]), float(fingers[i + 1])]
        velocity += [
            float(finger_speeds[i] + finger_speeds[i + 1]),
            float(finger_speeds[i]),
            float(finger_speeds[i + 1]),
        ]
        effort += [
            float(finger_forces[i] + finger_forces[i + 1]) / 2,
            float(finger_forces[i]),
            float(finger_forces[i + 1]),
        ]
    return {
        "header": {"stamp": stamp, "frame_id": ""},
        "name": list(JOINT_NAMES),
        "position": position,
        "velocity": velocity,
        "effort": effort,
    }


def _transform(stamp: Stamp, parent: str, child: str, pose: tuple[np.ndarray, np.ndarray]) -> Any:
    return {
        "header": {"stamp": stamp, "frame_id": parent},
        "child_frame_id": child,
        "transform": {"translation": _vector(pose[0]), "rotation": quaternion(pose[1])},
    }


def transforms(physics: Physics, stamp: Stamp) -> dict[str, Any]:
    """tf2_msgs/TFMessage: the base in odom, the other frames in base_footprint."""
    base = physics.frame(BASE)
    out = [_transform(stamp, ODOM, BASE, base)]
    out += [
        _transform(stamp, BASE, child, relative(base, physics.frame(child)))
        for child in TF_CHILDREN
    ]
    return {"transforms": out}


def _sees(physics: Physics, camera: Camera, name: str, thing: scene.Thing) -> bool:
    """Whether some point of the object is in the image with nothing in front of it."""
    ids = physics.ids
    m, d = physics.model.ptr, physics.data.ptr
    half = np.array(thing.size) / 2 * 0.8
    if thing.shape == "cylinder":
        half[:2] *= 0.7  # corners of the square inside the circle
    body = ids.bodies[name]
    points = d.xpos[body] + (_CORNERS * half) @ d.xmat[body].reshape(3, 3).T
    optical = camera.to_optical(physics, points)
    ahead = optical[:, 2] > NEAREST
    if not ahead.any():
        return False
    pixels = camera.project(physics, optical[ahead])
    inside = (
        (pixels[:, 0] >= 0)
        & (pixels[:, 0] <= camera.width - 1)
        & (pixels[:, 1] >= 0)
        & (pixels[:, 1] <= camera.height - 1)
    )
    origin = d.cam_xpos[ids.camera].copy()
    hit = np.zeros(1, dtype=np.int32)
    target = ids.objects[name]
    for point in points[ahead][inside]:
        mujoco.mj_ray(m, d, origin, point - origin, RAY_GROUPS, 1, ids.camera_body, hit)
        if hit[0] == target:
            return True
    return False


def detected_objects(
    physics: Physics, camera: Camera, plan: scene.Layout, stamp: Stamp
) -> dict[str, Any]:
    """lab_msgs/DetectedObjectArray: the objects in view, posed in base_footprint."""
    base = physics.frame(BASE)
    found = []
    for thing in plan.things:
        if not _sees(physics, camera, thing.name, thing):
            continue
        rotation = physics.data.xmat[physics.ids.bodies[thing.name]].reshape(3, 3)
        position, orientation = relative(base, (physics.object_position(thing.name), rotation))
        found.append(
            {
                "name": thing.name,
                "shape": thing.shape,
                "size": _vector(np.array(thing.size)),
                "pose": {"position": _vector(position), "orientation": quaternion(orientation)},
            }
        )
    return {"header": {"stamp": stamp, "frame_id": BASE}, "objects": found}


def goal(plan: scene.Layout, stamp: Stamp) -> dict[str, Any]:
    """lab_msgs/TableGoal: the object to move, the target area and the table, in odom."""
    hx, hy = scene.TABLE_HALF
    return {
        "header": {"stamp": stamp, "frame_id": ODOM},
        "object": plan.target,
        "target_center": {"x": plan.area[0], "y": plan.area[1], "z": scene.TABLE_TOP},
        "target_size": {"x": 2 * scene.AREA_HALF, "y": 2 * scene.AREA_HALF, "z": 0.0},
        "table_center": {
            "x": scene.TABLE_CENTER[0],
            "y": scene.TABLE_CENTER[1],
            "z": scene.TABLE_TOP,
        },
        "table_size": {"x": 2 * hx, "y": 2 * hy, "z": scene.TABLE_TOP},
    }
