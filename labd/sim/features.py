"""Each task's export layout: the named entries of its observation and action vectors.

An export (``repository.export``) has one row per control tick, and every row of a task
has these entries in this order, whichever topics the controller used, so the data of
different controllers and of people's demonstrations merge. Each entry is computed
from the record's messages (decoded with their own schemas); a command entry whose
topic had no message yet is its **neutral** value, what the robot does before any
command (stands still; holds its start pose). Entries constant by construction (an
odometry's z, its covariances) are left out. docs/tasks.md lists them with units.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any

from labd.sim.pr2 import model as pr2
from repository.export import Camera, Entry, Layout, Messages

CAMERA = Camera("camera", "/camera/image/compressed")
VERSION = "1"


def yaw(q: Any) -> float:
    """The rotation about z of a quaternion message."""
    return math.atan2(2 * (q.w * q.z + q.x * q.y), 1 - 2 * (q.y * q.y + q.z * q.z))


def field(
    topic: str, get: Callable[[Any], float], name: str, unit: str, doc: str, *, neutral: float = 0.0
) -> Entry:
    """An entry that is a function of the newest message of one topic."""

    def extract(messages: Messages, _topic: str) -> float | None:
        return float(get(messages[topic]))

    return Entry(name, (topic,), extract, neutral, unit, doc)


# -- icreate-maze --------------------------------------------------------------------------


def _goal_in_robot(messages: Messages) -> tuple[float, float] | None:
    odom, goal = messages.get("/odom"), messages.get("/goal")
    if odom is None or goal is None:
        return None
    pose = odom.pose.pose
    dx, dy = goal.point.x - pose.position.x, goal.point.y - pose.position.y
    heading = yaw(pose.orientation)
    return math.hypot(dx, dy), math.remainder(math.atan2(dy, dx) - heading, math.tau)


def _goal(i: int) -> Callable[[Messages, str], float | None]:
    def extract(messages: Messages, _topic: str) -> float | None:
        found = _goal_in_robot(messages)
        return None if found is None else found[i]

    return extract


def _nearest_tag(messages: Messages, what: str) -> float:
    tags = messages["/ar_tags"].tags
    if not tags:
        return 0.0
    tag = min(tags, key=lambda t: t.distance)
    if what == "distance":
        return float(tag.distance)
    p = tag.pose.position  # camera optical frame: z ahead, x right
    return math.atan2(-p.x, p.z)


def _wheel(part: str, joint: str) -> Callable[[Any], float]:
    def get(message: Any) -> float:
        return float(getattr(message, part)[list(message.name).index(joint)])

    return get


MAZE = Layout(
    task="icreate-maze",
    version=VERSION,
    observation=(
        field("/odom", lambda m: m.pose.pose.position.x, "odom.x", "m", "position in odom"),
        field("/odom", lambda m: m.pose.pose.position.y, "odom.y", "m", "position in odom"),
        field("/odom", lambda m: yaw(m.pose.pose.orientation), "odom.yaw", "rad", "heading"),
        field("/odom", lambda m: m.twist.twist.linear.x, "odom.linear", "m/s", "forward speed"),
        field("/odom", lambda m: m.twist.twist.angular.z, "odom.angular", "rad/s", "turn rate"),
        field(
            "/joint_states",
            _wheel("velocity", "left_wheel_joint"),
            "wheel.left.velocity",
            "rad/s",
            "left wheel speed",
        ),
        field(
            "/joint_states",
            _wheel("velocity", "right_wheel_joint"),
            "wheel.right.velocity",
            "rad/s",
            "right wheel speed",
        ),
        field(
            "/joint_states",
            _wheel("effort", "left_wheel_joint"),
            "wheel.left.effort",
            "N m",
            "left motor torque",
        ),
        field(
            "/joint_states",
            _wheel("effort", "right_wheel_joint"),
            "wheel.right.effort",
            "N m",
            "right motor torque",
        ),
        field("/bumper", lambda m: float(m.left), "bumper.left", "0/1", "left bumper pressed"),
        field("/bumper", lambda m: float(m.right), "bumper.right", "0/1", "right bumper pressed"),
        field("/goal", lambda m: m.point.x, "goal.x", "m", "the goal cell's centre in odom"),
        field("/goal", lambda m: m.point.y, "goal.y", "m", "the goal cell's centre in odom"),
        Entry(
            "goal.distance",
            ("/odom", "/goal"),
            _goal(0),
            0.0,
            "m",
            "straight-line distance from base_link to the goal",
        ),
        Entry(
            "goal.bearing",
            ("/odom", "/goal"),
            _goal(1),
            0.0,
            "rad",
            "direction of the goal from the robot's heading, counter-clockwise",
        ),
        field("/ar_tags", lambda m: len(m.tags), "tags.count", "", "tags seen"),
        field(
            "/ar_tags",
            lambda m: _nearest_tag({"/ar_tags": m}, "distance"),
            "tags.nearest.distance",
            "m",
            "the nearest seen tag's distance (0: none)",
        ),
        field(
            "/ar_tags",
            lambda m: _nearest_tag({"/ar_tags": m}, "bearing"),
            "tags.nearest.bearing",
            "rad",
            "its direction, counter-clockwise (0: none)",
        ),
    ),
    action=(
        field("/cmd_vel", lambda m: m.linear.x, "cmd_vel.linear.x", "m/s", "forward speed"),
        field("/cmd_vel", lambda m: m.angular.z, "cmd_vel.angular.z", "rad/s", "turn rate"),
    ),
    cameras=(CAMERA,),
    instruction=lambda _messages: "drive to the goal cell",
)


# -- pr2-table -----------------------------------------------------------------------------

ARM_JOINTS = (
    "shoulder_pan",
    "shoulder_lift",
    "upper_arm_roll",
    "elbow_flex",
    "forearm_roll",
    "wrist_flex",
    "wrist_roll",
)
SIDES = {"left": "l", "right": "r"}
SERVOED = (
    "torso_lift_joint",
    "head_pan_joint",
    "head_tilt_joint",
    *(f"{s}_{j}_joint" for s in "lr" for j in ARM_JOINTS),
    "l_gripper_joint",
    "r_gripper_joint",
)


def _joint(joint: str, part: str = "position") -> Entry:
    unit = "m" if joint in ("torso_lift_joint", "l_gripper_joint", "r_gripper_joint") else "rad"
    units = {"position": unit, "velocity": unit + "/s", "effort": "N"}
    return field(
        "/joint_states",
        _wheel(part, joint),
        f"joints.{joint}.{part}",
        units[part],
        f"{joint}'s {part}",
    )


def _frame(child: str, parent: str) -> Any:
    def find(message: Any) -> Any:
        for t in message.transforms:
            if t.child_frame_id == child and t.header.frame_id == parent:
                return t.transform
        raise LookupError(child)

    return find


def _tf(child: str, parent: str, what: str, name: str, doc: str) -> Entry:
    find = _frame(child, parent)

    def extract(messages: Messages, _topic: str) -> float | None:
        try:
            transform = find(messages["/tf"])
        except LookupError:
            return None
        if what == "yaw":
            return yaw(transform.rotation)
        return float(getattr(transform.translation, what))

    return Entry(name, ("/tf",), extract, 0.0, "rad" if what == "yaw" else "m", doc)


def _goal_object(what: str) -> Callable[[Messages, str], float | None]:
    def extract(messages: Messages, _topic: str) -> float | None:
        goal, seen = messages.get("/task/goal"), messages.get("/objects")
        if goal is None or seen is None:
            return None
        for obj in seen.objects:
            if obj.name == goal.object:
                return 1.0 if what == "visible" else float(getattr(obj.pose.position, what))
        return 0.0 if what == "visible" else None  # not seen: where it was last seen

    return extract


def _trajectory(topic: str, joint: str, name: str, neutral: float) -> Entry:
    def extract(messages: Messages, _topic: str) -> float | None:
        message = messages[topic]
        names = list(message.joint_names)
        if joint not in names or not message.points:
            return None  # this trajectory leaves the joint where it was told to be
        return float(message.points[-1].positions[names.index(joint)])

    unit = "m" if joint == "torso_lift_joint" else "rad"
    return Entry(
        name,
        (topic,),
        extract,
        neutral,
        unit,
        f"the last point of the newest trajectory naming {joint}",
    )


def _pose(side: str, what: str) -> Entry:
    pose_topic, trajectory_topic = f"/{side}_arm/pose", f"/{side}_arm/command"

    def extract(messages: Messages, topic: str) -> float | None:
        if what == "active":
            return 1.0 if topic == pose_topic else 0.0
        if topic != pose_topic:
            return None
        pose = messages[pose_topic].pose
        part = pose.orientation if what.startswith("q") else pose.position
        return float(getattr(part, what.removeprefix("q")))

    topics = (pose_topic, trajectory_topic) if what == "active" else (pose_topic,)
    doc = (
        "1 while a pose target drives the arm, 0 while a trajectory does"
        if what == "active"
        else "the newest pose target of the tool frame (in the frame it names)"
    )
    neutral = 1.0 if what == "qw" else 0.0
    unit = "" if what.startswith("q") or what == "active" else "m"
    return Entry(f"{side}_arm.pose.{what}", topics, extract, neutral, unit, doc)


def _instruction(messages: Messages) -> str:
    goal = messages.get("/task/goal")
    if goal is None:
        return "put the named object in the target area"
    return f"put the {str(goal.object).replace('_', ' ')} in the target area"


def _pr2_actions() -> tuple[Entry, ...]:
    entries = [
        field("/base/cmd_vel", lambda m: m.linear.x, "base.linear.x", "m/s", "base forward"),
        field("/base/cmd_vel", lambda m: m.linear.y, "base.linear.y", "m/s", "base left"),
        field("/base/cmd_vel", lambda m: m.angular.z, "base.angular.z", "rad/s", "base turn"),
        _trajectory("/torso/command", "torso_lift_joint", "torso.torso_lift_joint", 0.0),
        _trajectory("/head/command", "head_pan_joint", "head.head_pan_joint", pr2.HEAD_START[0]),
        _trajectory("/head/command", "head_tilt_joint", "head.head_tilt_joint", pr2.HEAD_START[1]),
    ]
    for side, s in SIDES.items():
        for joint, start in zip(ARM_JOINTS, pr2.TUCKED[s], strict=True):
            name = f"{s}_{joint}_joint"
            entries.append(_trajectory(f"/{side}_arm/command", name, f"{side}_arm.{name}", start))
    for side in SIDES:
        entries += [_pose(side, w) for w in ("active", "x", "y", "z", "qx", "qy", "qz", "qw")]
    for side in SIDES:
        entries.append(
            field(
                f"/{side}_gripper/command",
                lambda m: m.data,
                f"{side}_gripper.opening",
                "m",
                "the commanded opening",
            )
        )
    return tuple(entries)


def _pr2_observations() -> tuple[Entry, ...]:
    entries: list[Entry] = [_joint(j) for j in SERVOED]
    entries += [_joint(j, "velocity") for j in SERVOED]
    entries += [_joint(j, "effort") for j in ("l_gripper_joint", "r_gripper_joint")]
    entries += [
        _tf("base_footprint", "odom", "x", "base.x", "the base in odom"),
        _tf("base_footprint", "odom", "y", "base.y", "the base in odom"),
        _tf("base_footprint", "odom", "yaw", "base.yaw", "the base's heading in odom"),
    ]
    for s in "lr":
        for axis in "xyz":
            entries.append(
                _tf(
                    f"{s}_gripper_tool_frame",
                    "base_footprint",
                    axis,
                    f"{s}_tool.{axis}",
                    "the tool frame in base_footprint",
                )
            )
    for axis in "xyz":
        entries.append(
            Entry(
                f"object.{axis}",
                ("/objects", "/task/goal"),
                _goal_object(axis),
                0.0,
                "m",
                "the goal's object in base_footprint (where last seen)",
            )
        )
    entries.append(
        Entry(
            "object.visible",
            ("/objects", "/task/goal"),
            _goal_object("visible"),
            0.0,
            "0/1",
            "the goal's object is on /objects this tick",
        )
    )
    entries += [
        field("/task/goal", lambda m: m.target_center.x, "target.x", "m", "the area's centre"),
        field("/task/goal", lambda m: m.target_center.y, "target.y", "m", "the area's centre"),
    ]
    return tuple(entries)


PR2 = Layout(
    task="pr2-table",
    version=VERSION,
    observation=_pr2_observations(),
    action=_pr2_actions(),
    cameras=(CAMERA,),
    instruction=_instruction,
    instruction_topics=("/task/goal",),
)

LAYOUTS = {layout.task: layout for layout in (MAZE, PR2)}


def layout_of(task: str) -> Layout:
    """The export layout of ``task`` (KeyError for a task without one)."""
    return LAYOUTS[task]


def names(entries: Sequence[Entry]) -> list[str]:
    return [e.name for e in entries]
