"""``icreate-maze``: a Create-like robot finds the goal cell of a labmaze maze.

The seed draws the maze (``labmaze``), the start cell and heading, the tags on the
walls and their ids; the goal is the cell farthest from the start along the
corridors. The controller drives with ``/cmd_vel`` and sees through wheel odometry,
two front bumpers, a forward camera and a tag detector; ``/goal`` says where the
goal is in the odometry frame, so the task is to find a way there, not to guess
where it is. ``docs/tasks/icreate-maze.md`` is the reference for controller authors.

Reward per tick: the metres gained toward the goal along the maze's shortest path
(negative when moving away), plus ``SUCCESS_BONUS`` on reaching the goal cell,
which ends the episode.
"""

from __future__ import annotations

import functools
import math
from pathlib import Path
from typing import Any

import numpy as np
from dm_control import mujoco
from dm_control.rl import control
from dm_env import specs

from labd.sim.base import (
    CommandTopic,
    LabTask,
    ObservationTopic,
    Outcome,
    environment,
    finite,
)
from labd.sim.camera import Camera
from labd.sim.icreate import model
from labd.sim.icreate.export import MAZE
from labd.sim.icreate.layout import CELL, DIRECTIONS, Layout
from labd.sim.icreate.tags import Detector, Tag, place
from labd.sim.params import Param, Params
from labd.sim.registry import Actions, Console, Dimension, TaskSpec
from repository.evaluation import Suite
from repository.trial import EpisodeStatus

SUCCESS_BONUS = 10.0
BUMPER_OVERLAP = math.radians(15)  # contacts this close to dead ahead press both bumpers
CMD_VEL = "/cmd_vel"
# Optical frame (z ahead, x right, y down) in camera_link (x ahead, y left, z up).
OPTICAL_IN_CAMERA_LINK = {"x": -0.5, "y": 0.5, "z": -0.5, "w": 0.5}
# Fixed odometry covariances (row-major 6 x 6 diagonals): x, y, z, roll, pitch, yaw.
POSE_VARIANCE = (1e-3, 1e-3, 1e-9, 1e-9, 1e-9, 1e-2)
TWIST_VARIANCE = (1e-3, 1e-9, 1e-9, 1e-9, 1e-9, 1e-2)

PARAMS = Params(
    [
        Param("maze_size", 9, "the maze's side in cells, outer walls included", 5, 31, odd=True),
        Param("rooms", 2, "at most this many 3 x 3 rooms among the corridors", 0, 8),
        Param("tags", 12, "fiducial tags on the walls (fewer if the maze has no room)", 0, 200),
        Param("time_limit", 180.0, "seconds of simulation time before the episode ends", 1, 3600),
        Param(
            "control_rate",
            10,
            "control ticks per second",
            choices=(1, 2, 4, 5, 10, 20, 25, 50, 100),  # whole numbers of 2 ms steps
        ),
        Param("camera_width", 320, "camera image width, pixels", 16, 1280),
        Param("camera_height", 240, "camera image height, pixels", 16, 960),
    ]
)


class Physics(mujoco.Physics):  # type: ignore[misc]
    """The maze's physics, with the robot's state by name.

    The accessors run every tick, so they index MuJoCo's arrays by addresses looked
    up once rather than through ``named`` (which parses its key on every call).
    """

    @functools.cached_property
    def _addresses(self) -> dict[str, Any]:
        m = self.model
        wheels = [m.joint(name) for name in model.WHEEL_JOINTS]
        base = m.joint("base")
        return {
            "qpos": int(base.qposadr[0]),
            "qvel": int(base.dofadr[0]),
            "wheel_qpos": np.array([int(w.qposadr[0]) for w in wheels]),
            "wheel_dof": np.array([int(w.dofadr[0]) for w in wheels]),
            "shell": m.geom(model.SHELL).id,
            "body": m.body("base_link").id,
        }

    def base_pose(self) -> tuple[float, float, float]:
        """The robot's x, y (metres) and yaw (radians) in the world frame."""
        a = self._addresses["qpos"]
        x, y, _, w, qx, qy, qz = self.data.qpos[a : a + 7].tolist()
        yaw = math.atan2(2 * (w * qz + qx * qy), 1 - 2 * (qy * qy + qz * qz))
        return x, y, yaw

    def base_velocity(self) -> tuple[float, float]:
        """Forward speed (m/s) and yaw rate (rad/s), true values."""
        a = self._addresses["qvel"]
        vx, vy, _, _, _, wz = self.data.qvel[a : a + 6].tolist()
        _, _, yaw = self.base_pose()
        return vx * math.cos(yaw) + vy * math.sin(yaw), wz

    def wheel_angles(self) -> np.ndarray:
        """Left and right wheel angles (radians; positive rolls the robot forward)."""
        out: np.ndarray = self.data.qpos[self._addresses["wheel_qpos"]]
        return out

    def wheel_speeds(self) -> np.ndarray:
        """Left and right wheel angular speeds (rad/s)."""
        out: np.ndarray = self.data.qvel[self._addresses["wheel_dof"]]
        return out

    def wheel_torques(self) -> np.ndarray:
        """Torques the wheel motors apply now (N m)."""
        out: np.ndarray = self.data.qfrc_actuator[self._addresses["wheel_dof"]]
        return out

    def bumpers(self) -> tuple[bool, bool]:
        """Whether the left and right front bumpers are pressed.

        A bumper is pressed by a contact on the shell's front half: left of dead
        ahead presses the left one, right the right one, and within
        ``BUMPER_OVERLAP`` of dead ahead both, as on the Create.
        """
        if not self.data.ncon:
            return False, False
        shell = self._addresses["shell"]
        contacts = self.data.contact
        pairs = contacts.geom
        touching = (pairs[:, 0] == shell) | (pairs[:, 1] == shell)
        if not touching.any():
            return False, False
        body = self._addresses["body"]
        frame = self.data.xmat[body].reshape(3, 3)
        left = right = False
        for x, y, _ in ((contacts.pos[touching] - self.data.xpos[body]) @ frame).tolist():
            if x >= 0:  # the front half
                bearing = math.atan2(y, x)
                left = left or bearing >= -BUMPER_OVERLAP
                right = right or bearing <= BUMPER_OVERLAP
        return left, right


class IcreateMaze(LabTask):
    """Drive the robot from its start cell into the goal cell."""

    name = "icreate-maze"
    version = "1"
    params = PARAMS
    commands = (
        CommandTopic(
            CMD_VEL,
            "geometry_msgs/msg/Twist",
            "linear.x (m/s, |v| <= 0.5) and angular.z (rad/s, |w| <= 4.26) in base_link; "
            "kept until replaced; out of range is clipped and counted",
        ),
    )
    observations = (
        ObservationTopic("/odom", "nav_msgs/msg/Odometry", "wheel odometry, odom -> base_link"),
        ObservationTopic("/tf", "tf2_msgs/msg/TFMessage", "odom -> base_link"),
        ObservationTopic(
            "/tf_static",
            "tf2_msgs/msg/TFMessage",
            "base_link -> camera_link -> camera_optical_frame, once",
            period=0,
        ),
        ObservationTopic("/joint_states", "sensor_msgs/msg/JointState", "the two wheels"),
        ObservationTopic("/bumper", "lab_msgs/msg/Bumper", "left and right front bumpers"),
        ObservationTopic("/ar_tags", "lab_msgs/msg/ArTagArray", "tags the camera sees"),
        ObservationTopic("/camera/camera_info", "sensor_msgs/msg/CameraInfo", "intrinsics"),
        ObservationTopic(
            "/camera/image/compressed",
            "sensor_msgs/msg/CompressedImage",
            "the forward camera, JPEG",
            on_demand=True,
        ),
        ObservationTopic(
            "/goal", "geometry_msgs/msg/PointStamped", "the goal cell's centre in odom", period=0
        ),
    )

    def __init__(
        self,
        params: dict[str, Any],
        random: np.random.RandomState,
        layout: Layout,
        tags: list[Tag],
    ) -> None:
        super().__init__(params, random)
        self.layout = layout
        self.tags = tags
        self.camera = Camera(
            model.CAMERA,
            "camera_optical_frame",
            int(params["camera_width"]),
            int(params["camera_height"]),
        )
        self.detector = Detector(tags, self.camera)
        sx, sy = layout.centre(layout.start)
        dx, dy = DIRECTIONS[layout.heading]
        self.start = (sx, sy, math.atan2(dy, dx))  # the odom frame, in the world
        self.goal_odom = self.to_odom(*layout.centre(layout.goal))
        self._reset_state()

    def _reset_state(self) -> None:
        self.wheels = np.zeros(2)  # rim speeds the last /cmd_vel asks for, m/s
        self.odom = np.zeros(3)  # wheel odometry: x, y, yaw in the odom frame
        self.last_wheel_angles = np.zeros(2)
        self.bumped = False
        self.bumpers = (False, False)  # the pressed bumpers at the last tick
        self.collisions = 0
        self.path_length = 0.0
        self.last_xy = (self.start[0], self.start[1])
        self.to_goal = self.layout.distance_to_goal(*self.start[:2])
        self.reward = 0.0
        self.total_reward = 0.0
        self.succeeded = False

    def to_odom(self, x: float, y: float) -> tuple[float, float]:
        """A world point in the odom frame (the robot's pose at the start)."""
        sx, sy, yaw = self.start
        c, s = math.cos(yaw), math.sin(yaw)
        return c * (x - sx) + s * (y - sy), -s * (x - sx) + c * (y - sy)

    # -- dm_control ----------------------------------------------------------------------

    def initialize_episode(self, physics: Physics) -> None:
        """The robot at rest at the start. (No ``super()``: dm_control's calls
        ``after_step``, which would count a tick that never happened.)"""
        x, y, yaw = self.start
        physics.named.data.qpos["base"] = [x, y, 0.0, *model.yaw_quaternion(yaw)]
        physics.named.data.qpos[list(model.WHEEL_JOINTS)] = 0.0
        physics.data.qvel[:] = 0.0
        self._reset_state()

    def action_spec(self, physics: Physics) -> specs.BoundedArray:
        """Left and right wheel rim speeds, m/s."""
        top = model.MAX_WHEEL_SPEED
        return specs.BoundedArray((2,), np.float64, -top, top, name="wheel_speeds")

    def before_step(self, action: np.ndarray, physics: Physics) -> None:
        physics.set_control(action)

    def after_step(self, physics: Physics) -> None:
        """Odometry, collisions, path length and progress: once per control tick."""
        angles = physics.wheel_angles()
        left, right = (angles - self.last_wheel_angles) * model.WHEEL_RADIUS
        self.last_wheel_angles = angles
        ahead = (left + right) / 2
        turn = (right - left) / model.WHEEL_SEPARATION
        heading = self.odom[2] + turn / 2
        self.odom += (ahead * math.cos(heading), ahead * math.sin(heading), turn)
        self.odom[2] = math.remainder(self.odom[2], math.tau)

        self.bumpers = physics.bumpers()  # once a tick; observations reuse it
        bumped = any(self.bumpers)
        if bumped and not self.bumped:
            self.collisions += 1
        self.bumped = bumped

        x, y, _ = physics.base_pose()
        self.path_length += math.hypot(x - self.last_xy[0], y - self.last_xy[1])
        self.last_xy = (x, y)
        to_goal = self.layout.distance_to_goal(x, y)
        self.reward = self.to_goal - to_goal
        self.to_goal = to_goal
        if not self.succeeded and self.layout.cell_at(x, y) == self.layout.goal:
            self.succeeded = True
            self.reward += SUCCESS_BONUS
        self.total_reward += self.reward

    def get_observation(self, physics: Physics) -> dict[str, np.ndarray]:
        """True state in the odom frame, for agents in the same process."""
        x, y, yaw = physics.base_pose()
        ox, oy = self.to_odom(x, y)
        heading = yaw - self.start[2]
        gx, gy = self.goal_odom[0] - ox, self.goal_odom[1] - oy
        c, s = math.cos(heading), math.sin(heading)
        return {
            "position": np.array([ox, oy]),
            "heading": np.array([c, s]),
            "velocity": np.array(physics.base_velocity()),
            "bumpers": np.array(self.bumpers, dtype=np.float64),
            "goal": np.array([c * gx + s * gy, -s * gx + c * gy]),  # in base_link
        }

    def get_reward(self, physics: Physics) -> float:
        return self.reward

    def get_termination(self, physics: Physics) -> float | None:
        return 0.0 if self.succeeded else None

    # -- the ROS side ----------------------------------------------------------------------

    def command(self, topic: str, data: dict[str, Any]) -> None:
        """Keep a /cmd_vel: NaN refused, speeds clipped to the robot's (counted once)."""
        for part in ("linear", "angular"):
            for axis in ("x", "y", "z"):
                finite(data[part][axis], part, axis)
        linear = float(data["linear"]["x"])
        angular = float(data["angular"]["z"])
        top, turn = model.MAX_WHEEL_SPEED, model.MAX_TURN_RATE
        clipped_linear = min(max(linear, -top), top)
        clipped_angular = min(max(angular, -turn), turn)
        left, right = model.wheel_speeds(clipped_linear, clipped_angular)
        fastest = max(abs(left), abs(right))
        if fastest > top:  # keep the turn's radius, slow both wheels
            left, right = left * top / fastest, right * top / fastest
        if (clipped_linear, clipped_angular) != (linear, angular) or fastest > top:
            self.clipped[topic] = self.clipped.get(topic, 0) + 1
        self.wheels = np.array([left, right])

    def action(self, physics: Physics) -> np.ndarray:
        return self.wheels.copy()

    def observe(self, physics: Physics, topic: str, stamp: dict[str, int]) -> dict[str, Any] | None:
        header = {"stamp": stamp, "frame_id": "odom"}
        if topic == "/odom":
            return self._odometry(physics, header)
        if topic == "/tf":
            return {"transforms": [self._odom_transform(header)]}
        if topic == "/tf_static":
            return {"transforms": _static_transforms(stamp)}
        if topic == "/joint_states":
            return {
                "header": {"stamp": stamp, "frame_id": ""},
                "name": list(model.WHEEL_JOINTS),
                "position": physics.wheel_angles().tolist(),
                "velocity": physics.wheel_speeds().tolist(),
                "effort": physics.wheel_torques().tolist(),
            }
        if topic == "/bumper":
            left, right = self.bumpers
            return {
                "header": {"stamp": stamp, "frame_id": "base_link"},
                "left": left,
                "right": right,
            }
        if topic == "/ar_tags":
            frame = {"stamp": stamp, "frame_id": self.camera.frame_id}
            return {"header": frame, "tags": self.detector.detect(physics)}
        if topic == "/camera/camera_info":
            return self.camera.info(physics, stamp)
        if topic == "/camera/image/compressed":
            return self.camera.image(physics, stamp)
        if topic == "/goal":
            gx, gy = self.goal_odom
            return {"header": header, "point": {"x": gx, "y": gy, "z": 0.0}}
        raise KeyError(topic)

    def _odom_transform(self, header: dict[str, Any]) -> dict[str, Any]:
        x, y, yaw = self.odom
        return {
            "header": header,
            "child_frame_id": "base_link",
            "transform": {
                "translation": {"x": float(x), "y": float(y), "z": 0.0},
                "rotation": _yaw_quaternion(float(yaw)),
            },
        }

    def _odometry(self, physics: Physics, header: dict[str, Any]) -> dict[str, Any]:
        x, y, yaw = self.odom
        left, right = physics.wheel_speeds() * model.WHEEL_RADIUS
        return {
            "header": header,
            "child_frame_id": "base_link",
            "pose": {
                "pose": {
                    "position": {"x": float(x), "y": float(y), "z": 0.0},
                    "orientation": _yaw_quaternion(float(yaw)),
                },
                "covariance": _diagonal(POSE_VARIANCE),
            },
            "twist": {
                "twist": {
                    "linear": {"x": float(left + right) / 2, "y": 0.0, "z": 0.0},
                    "angular": {
                        "x": 0.0,
                        "y": 0.0,
                        "z": float(right - left) / model.WHEEL_SEPARATION,
                    },
                },
                "covariance": _diagonal(TWIST_VARIANCE),
            },
        }

    def outcome(self, physics: Physics) -> Outcome | None:
        if not self.succeeded:
            return None
        i, j = self.layout.goal
        x, y = self.to_odom(*physics.base_pose()[:2])
        return Outcome(
            EpisodeStatus.SUCCEEDED,
            f"reached the goal cell (row {i}, column {j}) at ({x:.2f}, {y:.2f}) in odom "
            f"after {physics.data.time:.1f} s",
        )

    def metrics(self, physics: Physics) -> dict[str, bool | int | float]:
        """``reward`` is the episode's total; ``distance_to_goal`` is along the corridors."""
        x, y, _ = physics.base_pose()
        return {
            "success": self.succeeded,
            "reward": self.total_reward,
            "distance_to_goal": self.layout.distance_to_goal(x, y),
            "collisions": self.collisions,
            "clipped_commands": sum(self.clipped.values()),
            "path_length": self.path_length,
        }


def _yaw_quaternion(yaw: float) -> dict[str, float]:
    return {"x": 0.0, "y": 0.0, "z": math.sin(yaw / 2), "w": math.cos(yaw / 2)}


def _diagonal(values: tuple[float, ...]) -> list[float]:
    out = [0.0] * 36
    for k, v in enumerate(values):
        out[7 * k] = v
    return out


def _static_transforms(stamp: dict[str, int]) -> list[dict[str, Any]]:
    cx, cy, cz = model.CAMERA_POS
    identity = {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}
    return [
        {
            "header": {"stamp": stamp, "frame_id": "base_link"},
            "child_frame_id": "camera_link",
            "transform": {"translation": {"x": cx, "y": cy, "z": cz}, "rotation": identity},
        },
        {
            "header": {"stamp": stamp, "frame_id": "camera_link"},
            "child_frame_id": "camera_optical_frame",
            "transform": {
                "translation": {"x": 0.0, "y": 0.0, "z": 0.0},
                "rotation": dict(OPTICAL_IN_CAMERA_LINK),
            },
        },
    ]


def make(
    values: dict[str, Any], seed: int, *, time_limit: float | None = None
) -> control.Environment:
    """One episode of the task: the maze, tags and start drawn from ``seed``."""
    rng = np.random.default_rng(seed)
    layout = Layout.generate(int(values["maze_size"]), int(values["rooms"]), rng)
    tags = place(layout, int(values["tags"]), rng)
    xml, assets = model.world_xml(
        layout, tags, int(values["camera_width"]), int(values["camera_height"])
    )
    physics = Physics.from_xml_string(xml, assets=assets)
    task = IcreateMaze(values, np.random.RandomState(int(rng.integers(2**31))), layout, tags)
    return environment(physics, task, xml=xml, assets=assets, time_limit=time_limit)


TWIST = {"linear": {"x": 0.0, "y": 0.0, "z": 0.0}, "angular": {"x": 0.0, "y": 0.0, "z": 0.0}}
# /cmd_vel as a vector (labd.gym, the generic live page): forward speed and turn rate.
ACTIONS = Actions(
    dimensions=(
        Dimension(
            "cmd_vel.linear.x", CMD_VEL, "linear.x", -model.MAX_WHEEL_SPEED, model.MAX_WHEEL_SPEED
        ),
        Dimension(
            "cmd_vel.angular.z", CMD_VEL, "angular.z", -model.MAX_TURN_RATE, model.MAX_TURN_RATE
        ),
    ),
    templates={CMD_VEL: ("geometry_msgs/msg/Twist", TWIST)},
)


TASK = TaskSpec(
    name=IcreateMaze.name,
    version=IcreateMaze.version,
    doc="A Create-like robot with a camera, bumpers and odometry finds the goal of a maze "
    f"({CELL:g} m cells) with fiducial tags on its walls.",
    params=PARAMS,
    build=make,
    task_class=IcreateMaze,
    live_params={"control_rate": 20},  # teleoperation: a 20 Hz camera and smoother driving
    playground=Path(__file__).with_name("playground.mjs"),
    layout=MAZE,
    camera=model.CAMERA,
    console=Console("robot_icreate.html", ("video", "perception")),
    robot="icreate-1",
    actions=ACTIONS,
    suites=(
        Suite("dev", 1, seeds=tuple(range(20)), doc="20 mazes, seeds 0 to 19, default parameters"),
        Suite("test", 1, episodes=50, held_out=True, doc="50 mazes whose seeds are the lab's"),
    ),
    normal_form=True,
)
