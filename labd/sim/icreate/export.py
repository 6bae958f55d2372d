"""The maze's export layout: its observation and action entries (docs/tasks.md)."""

from __future__ import annotations

import math
from collections.abc import Callable

from labd.sim.features import CAMERA, VERSION, field, joint_value, yaw
from repository.export import Entry, Layout, Messages


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
            joint_value("velocity", "left_wheel_joint"),
            "wheel.left.velocity",
            "rad/s",
            "left wheel speed",
        ),
        field(
            "/joint_states",
            joint_value("velocity", "right_wheel_joint"),
            "wheel.right.velocity",
            "rad/s",
            "right wheel speed",
        ),
        field(
            "/joint_states",
            joint_value("effort", "left_wheel_joint"),
            "wheel.left.effort",
            "N m",
            "left motor torque",
        ),
        field(
            "/joint_states",
            joint_value("effort", "right_wheel_joint"),
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
