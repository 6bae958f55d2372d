"""pr2-table: a PR2-like mobile manipulator moves a named object to an area on a table.

The robot (``model``) stands at the origin of ``odom`` facing a table (``scene``)
with one to six boxes and cylinders on it; the seed lays them out, names the one to
move and marks the target area. The episode succeeds when that object rests in the
area, and fails if it falls off the table.

Commands keep state that ``action`` turns into the dm_control action once a tick
(``motion``): the base's velocity, and setpoints for the torso, head, arm joints
and grippers that follow joint trajectories, Cartesian pose targets (solved by IK)
or gripper openings. Values out of range are clipped and counted per topic; NaN and
infinity are refused. The dm_control side (``action_spec``, ``get_observation``,
``get_reward``) is usable in-process without any of the ROS side.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from dm_control.rl import control
from dm_env import specs

from labd.errors import MessageError
from labd.sim.base import (
    CommandTopic,
    LabTask,
    ObservationTopic,
    Outcome,
    Stamp,
    environment,
    finite,
    random_state,
)
from labd.sim.camera import Camera
from labd.sim.params import Param, Params, Value
from labd.sim.pr2 import model, scene, topics
from labd.sim.pr2.export import PR2
from labd.sim.pr2.motion import ArmSolver, PoseTarget, Trajectory
from labd.sim.pr2.physics import BASE, ODOM, OPTICAL, SERVOED, TORSO, Physics
from labd.sim.registry import Actions, Console, Dimension, TaskSpec
from repository.evaluation import Suite
from repository.trial import EpisodeStatus

TIMESTEP = 0.002  # s: small enough for stable grasps
CONTROL_RATES = (10, 20, 25, 50, 100)  # Hz: each a whole number of physics steps
SETTLE_TIME = 0.5  # s the object must rest in the area before success is declared
STILL_LINEAR, STILL_ANGULAR = 0.02, 0.3  # m/s, rad/s: "nearly still"
FALLEN = 0.05  # m below the table top: the object has fallen off the table
SUCCESS_BONUS = 10.0

JOINT_TRAJECTORY = "trajectory_msgs/msg/JointTrajectory"
# The setpoint vector: SERVOED, then the two grippers' openings.
SETPOINT_JOINTS = (*SERVOED, model.GRIPPER["l"], model.GRIPPER["r"])
LOW = np.array([j.low for j in SETPOINT_JOINTS])
HIGH = np.array([j.high for j in SETPOINT_JOINTS])
SPEED = np.array([j.velocity for j in SETPOINT_JOINTS])
GROUPS = {  # trajectory topic -> indices of its joints in the setpoints
    "/torso/command": np.arange(0, 1),
    "/head/command": np.arange(1, 3),
    "/left_arm/command": np.arange(3, 10),
    "/right_arm/command": np.arange(10, 17),
}
ARM_TOPICS = {
    "l": ("/left_arm/command", "/left_arm/pose"),
    "r": ("/right_arm/command", "/right_arm/pose"),
}
GRIPPER_TOPICS = {"/left_gripper/command": "l", "/right_gripper/command": "r"}
GRIPPER_INDEX = {"l": 17, "r": 18}
POSE_FRAMES = (BASE, TORSO, ODOM)
BASE_LIMITS = np.array([model.BASE_LINEAR_MAX, model.BASE_LINEAR_MAX, model.BASE_ANGULAR_MAX])
ACTION_LOW = np.concatenate([-BASE_LIMITS, LOW])
ACTION_HIGH = np.concatenate([BASE_LIMITS, HIGH])
ACTION_SPEC = specs.BoundedArray(
    ACTION_LOW.shape,
    np.float64,
    ACTION_LOW,
    ACTION_HIGH,
    name="\t".join(("base_vx", "base_vy", "base_wz", *(j.name for j in SETPOINT_JOINTS))),
)

PARAMS = Params(
    [
        Param("objects", 3, "how many objects stand on the table", minimum=1, maximum=6),
        Param(
            "time_limit",
            120.0,
            "simulated seconds before the episode is cut off",
            minimum=1.0,
            maximum=3600.0,
        ),
        Param("control_rate", 20, "control ticks per simulated second (Hz)", choices=CONTROL_RATES),
        Param("camera_width", 320, "head camera image width (pixels)", minimum=32, maximum=1280),
        Param("camera_height", 240, "head camera image height (pixels)", minimum=24, maximum=960),
    ]
)


def _trajectory_doc(joints: str) -> str:
    return (
        f"joint trajectory for {joints}: joint_names (any of them), points with positions"
        " (rad or m) and time_from_start; followed by linear interpolation in simulation"
        " time from the tick it arrives; replaces the previous one; targets clipped to the"
        " joint limits and counted"
    )


class TableTask(LabTask):
    """Move the named object from where it stands into the target area."""

    name = "pr2-table"
    version = "1"
    params = PARAMS
    commands = (
        CommandTopic(
            "/base/cmd_vel",
            "geometry_msgs/msg/Twist",
            "base velocity in base_footprint: linear.x, linear.y (m/s, speed clipped to 0.5),"
            " angular.z (rad/s, clipped to 1.0); other fields clipped to 0; held until replaced",
        ),
        CommandTopic("/torso/command", JOINT_TRAJECTORY, _trajectory_doc("torso_lift_joint")),
        CommandTopic("/head/command", JOINT_TRAJECTORY, _trajectory_doc("the head pan and tilt")),
        CommandTopic("/left_arm/command", JOINT_TRAJECTORY, _trajectory_doc("the left arm")),
        CommandTopic("/right_arm/command", JOINT_TRAJECTORY, _trajectory_doc("the right arm")),
        CommandTopic(
            "/left_arm/pose",
            "geometry_msgs/msg/PoseStamped",
            "pose target for l_gripper_tool_frame, in base_footprint (or torso_lift_link,"
            " odom); reached by IK at up to 0.3 m/s; cancels /left_arm/command",
        ),
        CommandTopic(
            "/right_arm/pose",
            "geometry_msgs/msg/PoseStamped",
            "pose target for r_gripper_tool_frame, as /left_arm/pose",
        ),
        CommandTopic(
            "/left_gripper/command",
            "std_msgs/msg/Float64",
            "left gripper opening (m), clipped to 0..0.09; 0 closes it (squeezing what it holds)",
        ),
        CommandTopic("/right_gripper/command", "std_msgs/msg/Float64", "right gripper opening (m)"),
    )
    observations = (
        ObservationTopic(
            "/joint_states",
            "sensor_msgs/msg/JointState",
            "torso, head, arm joints (rad, m), each gripper's gap and fingers (m)",
        ),
        ObservationTopic(
            "/tf",
            "tf2_msgs/msg/TFMessage",
            "odom -> base_footprint -> torso_lift_link, head_camera_optical_frame,"
            " l_gripper_tool_frame, r_gripper_tool_frame",
        ),
        ObservationTopic(
            "/camera/image/compressed",
            "sensor_msgs/msg/CompressedImage",
            "the head camera, JPEG, in head_camera_optical_frame",
            on_demand=True,
        ),
        ObservationTopic(
            "/camera/camera_info", "sensor_msgs/msg/CameraInfo", "the head camera's intrinsics"
        ),
        ObservationTopic(
            "/objects",
            "lab_msgs/msg/DetectedObjectArray",
            "objects the head camera sees (in its image, not hidden), posed in base_footprint",
        ),
        ObservationTopic(
            "/task/goal",
            "lab_msgs/msg/TableGoal",
            "the object to move and the target area, in odom (once, latched)",
            period=0,
        ),
    )

    def __init__(
        self, params: Mapping[str, Value], random: np.random.RandomState, plan: scene.Layout
    ) -> None:
        super().__init__(params, random)
        self.plan = plan
        self.dt = 1.0 / int(params["control_rate"])
        self.settle_ticks = math.ceil(SETTLE_TIME / self.dt - 1e-9)
        self.camera = Camera(
            model.CAMERA, OPTICAL, int(params["camera_width"]), int(params["camera_height"])
        )
        self.solvers: dict[str, ArmSolver] = {}
        self._reset()

    def _reset(self) -> None:
        self.clipped.clear()
        self.base_command = np.zeros(3)
        self.setpoints = np.zeros(len(SETPOINT_JOINTS))
        self.trajectories: dict[str, Trajectory] = {}
        self.poses: dict[str, PoseTarget] = {}
        self.gripper_targets = {"l": 0.0, "r": 0.0}
        self.settled = 0  # consecutive ticks the object has rested in the area
        self.reward = 0.0  # of the last tick
        self.total_reward = 0.0

    # -- dm_control ----------------------------------------------------------------------

    def initialize_episode(self, physics: Physics) -> None:
        """The robot at the origin, arms tucked, head on the table; objects as laid out.

        The layout was drawn from the task's random state when the model was built (the
        model depends on it). dm_control's own ``initialize_episode`` is not called: it
        only runs ``after_step``, which here counts ticks of rest.
        """
        self._reset()
        ids = physics.ids
        start = np.concatenate(
            [[0.0], model.HEAD_START, model.TUCKED["l"], model.TUCKED["r"], [0.0, 0.0]]
        )
        physics.data.qpos[ids.base_qpos] = 0.0
        physics.data.act[ids.base_acts] = 0.0
        physics.data.qpos[ids.servo_qpos] = start[:17]
        physics.data.qpos[ids.finger_qpos] = 0.0
        for thing in self.plan.things:
            adr = physics.model.jnt_qposadr[physics.model.name2id(thing.name, "joint")]
            half = thing.yaw / 2
            physics.data.qpos[adr : adr + 7] = [
                *(thing.x, thing.y, thing.rest_z),
                *(math.cos(half), 0.0, 0.0, math.sin(half)),
            ]
        self.setpoints = start
        self.solvers = {side: ArmSolver(physics.model.ptr, side) for side in model.SIDES}
        self.before_step(self._action(), physics)

    def action_spec(self, physics: Physics) -> specs.BoundedArray:
        """Base velocity (vx, vy m/s; wz rad/s, base frame), then setpoints: torso (m),
        head pan, tilt, left arm, right arm (rad), left and right gripper openings (m)."""
        return ACTION_SPEC

    def before_step(self, action: np.ndarray, physics: Physics) -> None:
        """Set the actuators: the base velocity turned into odom, servo targets as given."""
        action = np.clip(np.asarray(action, dtype=np.float64), ACTION_LOW, ACTION_HIGH)
        ids = physics.ids
        data = physics.data
        base = data.qpos[ids.base_qpos]
        c, s = math.cos(base[2]), math.sin(base[2])
        vx, vy, wz = action[:3]
        velocity = (c * vx - s * vy, s * vx + c * vy, wz)
        data.ctrl[ids.base_actuators] = velocity
        data.ctrl[ids.base_holds] = velocity
        slack = model.BASE_HOLD_SLACK
        data.act[ids.base_acts] = np.clip(data.act[ids.base_acts], base - slack, base + slack)
        data.ctrl[ids.servo_actuators] = action[3:20]
        data.ctrl[ids.finger_actuators] = np.repeat(action[20:22] / 2, 2)

    def after_step(self, physics: Physics) -> None:
        """Judge the tick: how long the object has rested in the area, and the reward."""
        self.settled = self.settled + 1 if self._resting(physics) else 0
        self.reward = self._shaped(physics)
        if self.settled == self.settle_ticks:
            self.reward += SUCCESS_BONUS
        self.total_reward += self.reward

    def get_observation(self, physics: Physics) -> OrderedDict[str, np.ndarray]:
        """Ground truth for in-process agents (a ROS controller sees only the topics)."""
        target = self.plan.target
        return OrderedDict(
            base_pose=physics.base_pose(),
            base_velocity=physics.base_velocity(),
            joint_positions=np.concatenate([physics.servo_positions(), physics.gripper_openings()]),
            joint_velocities=physics.servo_velocities(),
            tool_positions=np.concatenate([physics.tool_position(s) for s in model.SIDES]),
            object_poses=np.concatenate(
                [
                    np.concatenate(
                        [physics.object_position(t.name), physics.object_quaternion(t.name)]
                    )
                    for t in self.plan.things
                ]
            ),
            target_object=np.concatenate(
                [physics.object_position(target), physics.object_quaternion(target)]
            ),
            target_area=np.array(self.plan.area),
        )

    def get_reward(self, physics: Physics) -> float:
        """This tick's reward (``after_step`` computes it)."""
        return self.reward

    def _shaped(self, physics: Physics) -> float:
        """In [0, 1]: 0.3 for a tool frame near the object, 0.7 for the object near the
        area's centre (each 1 - tanh(5 d), d in m)."""
        position = physics.object_position(self.plan.target)
        reach = min(float(np.linalg.norm(physics.tool_position(s) - position)) for s in "lr")
        place = self._distance(physics)
        return 0.3 * (1 - math.tanh(5 * reach)) + 0.7 * (1 - math.tanh(5 * place))

    def get_termination(self, physics: Physics) -> float | None:
        return 0.0 if self.outcome(physics) is not None else None

    # -- judging -----------------------------------------------------------------------

    def _distance(self, physics: Physics) -> float:
        """Horizontal distance (m) from the object's centre to the area's."""
        x, y, _ = physics.object_position(self.plan.target)
        return math.hypot(x - self.plan.area[0], y - self.plan.area[1])

    def _resting(self, physics: Physics) -> bool:
        """In the area, touching the table, nearly still, touched by no finger."""
        name = self.plan.target
        x, y, _ = physics.object_position(name)
        ax, ay = self.plan.area
        if abs(x - ax) > scene.AREA_HALF or abs(y - ay) > scene.AREA_HALF:
            return False
        linear, angular = physics.object_speed(name)
        if linear > STILL_LINEAR or angular > STILL_ANGULAR:
            return False
        return physics.on_table(name) and not physics.held(name)

    def _fallen(self, physics: Physics) -> bool:
        name = self.plan.target
        low = physics.object_position(name)[2] < scene.TABLE_TOP - FALLEN
        return bool(low and not physics.held(name))

    def outcome(self, physics: Physics) -> Outcome | None:
        name = self.plan.target
        if self.settled >= self.settle_ticks:
            off = self._distance(physics)
            when = float(physics.data.time)
            return Outcome(
                EpisodeStatus.SUCCEEDED,
                f"the {name} rests in the target area, {off:.3f} m from its centre,"
                f" at {when:.1f} s",
            )
        if self._fallen(physics):
            return Outcome(EpisodeStatus.FAILED, f"the {name} fell off the table")
        return None

    def metrics(self, physics: Physics) -> dict[str, bool | int | float]:
        """``reward`` is the episode's total; ``object_to_target`` horizontal, in m."""
        return {
            "success": self.settled >= self.settle_ticks,
            "reward": self.total_reward,
            "object_to_target": self._distance(physics),
            "dropped": self._fallen(physics),
            "clipped_commands": sum(self.clipped.values()),
        }

    # -- commands ------------------------------------------------------------------------

    def command(self, topic: str, data: dict[str, Any]) -> None:
        """Check a command whole, then keep it; a message with any value out of range is
        clipped and counts once in ``clipped`` (a refused one changes nothing)."""
        if topic == "/base/cmd_vel":
            self._twist(topic, data)
        elif topic in GROUPS:
            self._trajectory(topic, data)
        elif topic in GRIPPER_TOPICS:
            opening = finite(data["data"], "data")
            self.gripper_targets[GRIPPER_TOPICS[topic]] = self._clip(
                topic, np.array([opening]), np.zeros(1), np.array([model.GRIPPER_MAX])
            )[0]
        elif topic in ("/left_arm/pose", "/right_arm/pose"):
            self._pose(topic, data)
        else:
            raise MessageError(f"is not a command topic of {self.name}", [topic])

    def _clip(self, topic: str, values: np.ndarray, low: np.ndarray, high: np.ndarray) -> Any:
        """``values`` within ``[low, high]``; a message that needed it counts once."""
        clipped = np.clip(values, low, high)
        if np.any(clipped != values):
            self.clipped[topic] = self.clipped.get(topic, 0) + 1
        return clipped

    def _twist(self, topic: str, data: dict[str, Any]) -> None:
        values = {
            (part, axis): finite(data[part][axis], part, axis)
            for part in ("linear", "angular")
            for axis in "xyz"
        }
        vx, vy, wz = values["linear", "x"], values["linear", "y"], values["angular", "z"]
        speed = math.hypot(vx, vy)
        scale = min(1.0, model.BASE_LINEAR_MAX / speed) if speed > 0 else 1.0
        turn = min(max(wz, -model.BASE_ANGULAR_MAX), model.BASE_ANGULAR_MAX)
        # The base cannot move along z nor tilt: those fields are clipped to 0.
        impossible = (values["linear", "z"], values["angular", "x"], values["angular", "y"])
        if scale < 1.0 or turn != wz or any(impossible):
            self.clipped[topic] = self.clipped.get(topic, 0) + 1
        self.base_command = np.array([vx * scale, vy * scale, turn])

    def _trajectory(self, topic: str, data: dict[str, Any]) -> None:
        indices = GROUPS[topic]
        known = {SETPOINT_JOINTS[i].name: int(i) for i in indices}
        names = list(data["joint_names"])
        chosen: list[int] = []
        for i, name in enumerate(names):
            if name not in known:
                raise MessageError(
                    f"must be one of {', '.join(known)}, got {name!r}", ["joint_names", i]
                )
            if known[name] in chosen:
                raise MessageError(f"names {name!r} twice", ["joint_names", i])
            chosen.append(known[name])
        times: list[float] = []
        rows: list[list[float]] = []
        for p, point in enumerate(data["points"]):
            for field in ("velocities", "accelerations", "effort"):  # not used, but checked
                for j, value in enumerate(point[field]):
                    finite(float(value), "points", p, field, j)
            positions = [
                finite(float(v), "points", p, "positions", j)
                for j, v in enumerate(point["positions"])
            ]
            if len(positions) != len(names):
                raise MessageError(
                    f"must have one position per joint name ({len(names)}), got {len(positions)}",
                    ["points", p, "positions"],
                )
            stamp = point["time_from_start"]
            at = stamp["sec"] + stamp["nanosec"] * 1e-9
            if at < 0 or (times and at < times[-1]):
                raise MessageError(
                    "must be at least 0 and not earlier than the point before",
                    ["points", p, "time_from_start"],
                )
            times.append(at)
            rows.append(positions)
        side = next((s for s, (joint_topic, _) in ARM_TOPICS.items() if joint_topic == topic), None)
        if side is not None:
            self.poses.pop(side, None)  # a joint command cancels a pose command
        if not rows or not chosen:  # an empty trajectory stops the joints where they are
            self.trajectories.pop(topic, None)
            return
        joints = np.array(chosen)
        points = self._clip(topic, np.array(rows, dtype=np.float64), LOW[joints], HIGH[joints])
        self.trajectories[topic] = Trajectory(joints, np.array(times), points)

    def _pose(self, topic: str, data: dict[str, Any]) -> None:
        frame = data["header"]["frame_id"] or BASE
        if frame not in POSE_FRAMES:
            raise MessageError(
                f"must be one of {', '.join(POSE_FRAMES)}, got {frame!r}", ["header", "frame_id"]
            )
        p, o = data["pose"]["position"], data["pose"]["orientation"]
        position = np.array([finite(p[a], "pose", "position", a) for a in "xyz"])
        quat = np.array([finite(o[a], "pose", "orientation", a) for a in "wxyz"])
        norm = float(np.linalg.norm(quat))
        if norm < 1e-6:
            raise MessageError(
                "must be a unit quaternion, got one of length 0", ["pose", "orientation"]
            )
        w, x, y, z = quat / norm
        rotation = np.array(
            [
                [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
            ]
        )
        side = "l" if topic == "/left_arm/pose" else "r"
        self.trajectories.pop(ARM_TOPICS[side][0], None)  # a pose command cancels a trajectory
        self.poses[side] = PoseTarget(frame, position, rotation)

    # -- the action ----------------------------------------------------------------------

    def action(self, physics: Physics) -> np.ndarray:
        """Advance the setpoints one tick toward what the commands ask, within speed limits."""
        now = float(physics.data.time)
        reference = self.setpoints.copy()
        for trajectory in self.trajectories.values():
            reference[trajectory.indices] = trajectory.reference(now, self.setpoints)
        for side, index in GRIPPER_INDEX.items():
            reference[index] = self.gripper_targets[side]
        step = np.clip(reference - self.setpoints, -SPEED * self.dt, SPEED * self.dt)
        setpoints = self.setpoints + step
        for side, target in self.poses.items():
            indices = GROUPS[ARM_TOPICS[side][0]]
            origin, turn = physics.frame(target.frame)
            qpos = physics.data.qpos.copy()
            qpos[physics.ids.servo_qpos] = setpoints[:17]
            setpoints[indices] = self.solvers[side].step(
                qpos,
                self.setpoints[indices],
                origin + turn @ target.position,
                turn @ target.rotation,
                dt=self.dt,
                speed=SPEED[indices],
            )
        self.setpoints = np.clip(setpoints, LOW, HIGH)
        return self._action()

    def _action(self) -> np.ndarray:
        return np.concatenate([self.base_command, self.setpoints])

    # -- observations --------------------------------------------------------------------

    def observe(self, physics: Physics, topic: str, stamp: Stamp) -> dict[str, Any] | None:
        if topic == "/joint_states":
            return topics.joint_state(physics, stamp)
        if topic == "/tf":
            return topics.transforms(physics, stamp)
        if topic == "/objects":
            return topics.detected_objects(physics, self.camera, self.plan, stamp)
        if topic == "/camera/image/compressed":
            return self.camera.image(physics, stamp)
        if topic == "/camera/camera_info":
            return self.camera.info(physics, stamp)
        if topic == "/task/goal":
            return topics.goal(self.plan, stamp)
        return None


def make(
    values: Mapping[str, Value], seed: int, *, time_limit: float | None = None
) -> control.Environment:
    """One pr2-table episode: the layout, hence the model, is drawn from ``seed``."""
    random = random_state(seed)
    plan = scene.layout(random, int(values["objects"]))
    xml = scene.world_xml(
        plan,
        timestep=TIMESTEP,
        width=int(values["camera_width"]),
        height=int(values["camera_height"]),
    )
    physics = Physics.from_xml_string(xml)
    task = TableTask(values, random, plan)
    return environment(physics, task, xml=xml, time_limit=time_limit)


def _trajectory(joints: tuple[model.Joint, ...], start: Sequence[float]) -> dict[str, Any]:
    """A one-point JointTrajectory to ``start``, reached within one tick at 10 Hz."""
    point = {"positions": list(start), "time_from_start": {"sec": 0, "nanosec": 100_000_000}}
    return {"joint_names": [j.name for j in joints], "points": [point]}


def _actions() -> Actions:
    """The PR2's commands as a vector (labd.gym, the generic live page): base velocity,
    then joint position targets (torso, head, left arm, right arm), then grippers."""
    base = (
        Dimension(
            "base.linear.x",
            "/base/cmd_vel",
            "linear.x",
            -model.BASE_LINEAR_MAX,
            model.BASE_LINEAR_MAX,
        ),
        Dimension(
            "base.linear.y",
            "/base/cmd_vel",
            "linear.y",
            -model.BASE_LINEAR_MAX,
            model.BASE_LINEAR_MAX,
        ),
        Dimension(
            "base.angular.z",
            "/base/cmd_vel",
            "angular.z",
            -model.BASE_ANGULAR_MAX,
            model.BASE_ANGULAR_MAX,
        ),
    )
    groups = {
        "/torso/command": ((model.TORSO,), (0.0,)),
        "/head/command": (model.HEAD, model.HEAD_START),
        "/left_arm/command": (model.ARMS["l"], model.TUCKED["l"]),
        "/right_arm/command": (model.ARMS["r"], model.TUCKED["r"]),
    }
    joints = tuple(
        Dimension(joint.name, topic, f"points.0.positions.{i}", joint.low, joint.high, start)
        for topic, (group, starts) in groups.items()
        for i, (joint, start) in enumerate(zip(group, starts, strict=True))
    )
    grippers = tuple(
        Dimension(
            f"{side}_gripper.opening", f"/{side}_gripper/command", "data", 0.0, model.GRIPPER_MAX
        )
        for side in ("left", "right")
    )
    twist = {"linear": {"x": 0.0, "y": 0.0, "z": 0.0}, "angular": {"x": 0.0, "y": 0.0, "z": 0.0}}
    templates: dict[str, tuple[str, Mapping[str, Any]]] = {
        "/base/cmd_vel": ("geometry_msgs/msg/Twist", twist)
    }
    for topic, (group, starts) in groups.items():
        templates[topic] = (JOINT_TRAJECTORY, _trajectory(group, starts))
    for side in ("left", "right"):
        templates[f"/{side}_gripper/command"] = ("std_msgs/msg/Float64", {"data": 0.0})
    return Actions(dimensions=(*base, *joints, *grippers), templates=templates)


TASK = TaskSpec(
    name=TableTask.name,
    version=TableTask.version,
    doc=(
        "A PR2-like mobile manipulator (omnidirectional base, torso lift, two 7-joint arms"
        " with parallel grippers, pan-tilt head camera) in front of a table with boxes and"
        " cylinders: pick the named object and place it in the target area."
    ),
    params=PARAMS,
    build=make,
    task_class=TableTask,
    playground=Path(__file__).with_name("playground.mjs"),
    layout=PR2,
    camera=model.CAMERA,
    console=Console("robot_pr2.html", ("scene",)),
    robot="pr2-1",
    actions=_actions(),
    suites=(
        Suite("dev", 1, seeds=tuple(range(20)), doc="20 tables, seeds 0 to 19, default parameters"),
        Suite("test", 1, episodes=50, held_out=True, doc="50 tables whose seeds are the lab's"),
    ),
    normal_form=True,
)
