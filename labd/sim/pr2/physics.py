"""The pr2-table physics: MuJoCo with accessors by name for the robot and the objects.

Names are looked up once (``ids``); the accessors then index arrays directly, so
the task can call them every tick without dm_control's slower named indexing.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import mujoco
import numpy as np
from dm_control.mujoco import Physics as _Physics

from labd.sim.pr2 import model

ODOM = "odom"
BASE = "base_footprint"
TORSO = "torso_lift_link"
OPTICAL = "head_camera_optical_frame"
TOOLS = {side: f"{side}_gripper_tool_frame" for side in model.SIDES}
# The servo-driven joints, in the order of the setpoints (and of the action after the base).
SERVOED = (model.TORSO, *model.HEAD, *model.ARMS["l"], *model.ARMS["r"])
FINGERS = tuple(f"{side}_gripper_{which}_finger_joint" for side in model.SIDES for which in "lr")
# MuJoCo's camera looks along -z with y up; the ROS optical frame along z with y down.
_OPTICAL_FLIP = np.diag([1.0, -1.0, -1.0])


@dataclass(frozen=True)
class Ids:
    """Indices into the model's arrays, found once by name."""

    base_qpos: np.ndarray  # x, y, yaw
    base_qvel: np.ndarray
    base_actuators: np.ndarray  # velocity x, y, yaw
    base_holds: np.ndarray  # their integrated twins: actuator ids
    base_acts: np.ndarray  # and the holds' activations (where the base should be)
    servo_qpos: np.ndarray  # SERVOED
    servo_qvel: np.ndarray
    servo_actuators: np.ndarray
    finger_qpos: np.ndarray  # FINGERS: l gripper's two, then r's
    finger_qvel: np.ndarray
    finger_actuators: np.ndarray
    bodies: dict[str, int]
    sites: dict[str, int]
    camera: int
    camera_body: int
    table: int  # the table top's geom
    pads: dict[str, tuple[int, ...]]  # each gripper's finger pads
    objects: dict[str, int]  # object name -> its geom (body and free joint share the name)
    object_qvel: dict[str, int]


def _joint_addresses(m: mujoco.MjModel, names: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray]:
    ids = [m.joint(n).id for n in names]
    return np.array([m.jnt_qposadr[i] for i in ids]), np.array([m.jnt_dofadr[i] for i in ids])


class Physics(_Physics):  # type: ignore[misc]
    """MuJoCo physics of the robot, the table and its objects."""

    @functools.cached_property
    def ids(self) -> Ids:
        m = self.model.ptr
        base_qpos, base_qvel = _joint_addresses(m, model.BASE_JOINTS)
        servo_names = tuple(j.name for j in SERVOED)
        servo_qpos, servo_qvel = _joint_addresses(m, servo_names)
        finger_qpos, finger_qvel = _joint_addresses(m, FINGERS)
        objects = {
            m.geom(i).name: i
            for i in range(m.ngeom)
            if m.body_jntnum[m.geom_bodyid[i]] and m.jnt_type[m.body_jntadr[m.geom_bodyid[i]]] == 0
        }
        return Ids(
            base_qpos=base_qpos,
            base_qvel=base_qvel,
            base_actuators=np.array([m.actuator(n).id for n, *_ in model.BASE_SERVOS]),
            base_holds=np.array([m.actuator(f"{n}_hold").id for n, *_ in model.BASE_SERVOS]),
            base_acts=np.array(
                [m.actuator_actadr[m.actuator(f"{n}_hold").id] for n, *_ in model.BASE_SERVOS]
            ),
            servo_qpos=servo_qpos,
            servo_qvel=servo_qvel,
            servo_actuators=np.array([m.actuator(n).id for n in servo_names]),
            finger_qpos=finger_qpos,
            finger_qvel=finger_qvel,
            finger_actuators=np.array([m.actuator(n).id for n in FINGERS]),
            bodies={n: m.body(n).id for n in (BASE, TORSO, *objects)},
            sites={n: m.site(n).id for n in TOOLS.values()},
            camera=m.camera(model.CAMERA).id,
            camera_body=m.body(model.CAMERA_BODY).id,
            table=m.geom("table").id,
            pads={s: tuple(m.geom(n).id for n in model.finger_pads(s)) for s in model.SIDES},
            objects=objects,
            object_qvel={n: int(m.jnt_dofadr[m.joint(n).id]) for n in objects},
        )

    # -- the robot ---------------------------------------------------------------------

    def base_pose(self) -> np.ndarray:
        """x, y (m) and yaw (rad) of base_footprint in odom."""
        pose: np.ndarray = self.data.qpos[self.ids.base_qpos].copy()
        return pose

    def base_velocity(self) -> np.ndarray:
        """The base's velocity in its own frame: forward, left (m/s) and turning (rad/s)."""
        vx, vy, wz = self.data.qvel[self.ids.base_qvel]
        yaw = self.data.qpos[self.ids.base_qpos[2]]
        c, s = np.cos(yaw), np.sin(yaw)
        return np.array([c * vx + s * vy, -s * vx + c * vy, wz])

    def servo_positions(self) -> np.ndarray:
        """Torso (m), head pan and tilt, left arm, right arm (rad): SERVOED's order."""
        out: np.ndarray = self.data.qpos[self.ids.servo_qpos].copy()
        return out

    def servo_velocities(self) -> np.ndarray:
        out: np.ndarray = self.data.qvel[self.ids.servo_qvel].copy()
        return out

    def servo_efforts(self) -> np.ndarray:
        """The servos' forces and torques (N, N m)."""
        out: np.ndarray = self.data.actuator_force[self.ids.servo_actuators].copy()
        return out

    def finger_positions(self) -> np.ndarray:
        out: np.ndarray = self.data.qpos[self.ids.finger_qpos].copy()
        return out

    def finger_velocities(self) -> np.ndarray:
        out: np.ndarray = self.data.qvel[self.ids.finger_qvel].copy()
        return out

    def finger_forces(self) -> np.ndarray:
        out: np.ndarray = self.data.actuator_force[self.ids.finger_actuators].copy()
        return out

    def gripper_openings(self) -> np.ndarray:
        """The gap between each gripper's fingers (m): left, right."""
        q = self.data.qpos[self.ids.finger_qpos]
        return np.array([q[0] + q[1], q[2] + q[3]])

    def frame(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        """Position and rotation matrix in odom of a frame the task publishes."""
        ids = self.ids
        if name == ODOM:
            return np.zeros(3), np.eye(3)
        if name in ids.sites:
            site = ids.sites[name]
            return self.data.site_xpos[site].copy(), self.data.site_xmat[site].reshape(3, 3).copy()
        if name == OPTICAL:
            cam = ids.camera
            mat = self.data.cam_xmat[cam].reshape(3, 3) @ _OPTICAL_FLIP
            return self.data.cam_xpos[cam].copy(), mat
        body = ids.bodies[name]
        return self.data.xpos[body].copy(), self.data.xmat[body].reshape(3, 3).copy()

    def tool_position(self, side: str) -> np.ndarray:
        out: np.ndarray = self.data.site_xpos[self.ids.sites[TOOLS[side]]].copy()
        return out

    # -- the objects -------------------------------------------------------------------

    def object_position(self, name: str) -> np.ndarray:
        out: np.ndarray = self.data.xpos[self.ids.bodies[name]].copy()
        return out

    def object_quaternion(self, name: str) -> np.ndarray:
        """w, x, y, z in odom."""
        out: np.ndarray = self.data.xquat[self.ids.bodies[name]].copy()
        return out

    def object_speed(self, name: str) -> tuple[float, float]:
        """Linear (m/s) and angular (rad/s) speed of an object."""
        adr = self.ids.object_qvel[name]
        qvel = self.data.qvel
        return float(np.linalg.norm(qvel[adr : adr + 3])), float(
            np.linalg.norm(qvel[adr + 3 : adr + 6])
        )

    def touching(self, geom: int, others: tuple[int, ...]) -> bool:
        """Whether ``geom`` is in contact with any of ``others`` now."""
        n = self.data.ncon
        if n == 0:
            return False
        g1 = self.data.contact.geom1[:n]
        g2 = self.data.contact.geom2[:n]
        wanted = np.array(others)
        return bool(
            np.any((g1 == geom) & np.isin(g2, wanted)) or np.any((g2 == geom) & np.isin(g1, wanted))
        )

    def held(self, name: str) -> bool:
        """Whether a finger pad of either gripper touches the object."""
        pads = self.ids.pads["l"] + self.ids.pads["r"]
        return self.touching(self.ids.objects[name], pads)

    def on_table(self, name: str) -> bool:
        return self.touching(self.ids.objects[name], (self.ids.table,))
