"""The PR2 table's export layout: its observation and action entries (docs/tasks.md)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from labd.sim.features import CAMERA, VERSION, field, joint_value, yaw
from labd.sim.pr2 import model as pr2
from repository.export import Entry, Layout, Messages

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
        joint_value(part, joint),
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
