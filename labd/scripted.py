"""Scripted demonstrations: a driver that knows the maze drives a live robot, recorded.

People demonstrate a task by driving a live robot from its page (``labd.live``); a
test, a benchmark or a tutorial that needs demonstrations without a person uses this
driver instead. It drives the same way a page does: a client node of the robot's graph
takes the robot (``Driving.take``: a new episode, recorded), publishes ``/cmd_vel``
each tick, and the drive is filed as a ``demonstration`` when its episode ends. What it
knows is privileged: the maze's layout and the robot's true pose (the planner's moves
along the shortest path), which is what a person watching the camera and the map has.
The robot is stepped here, in the caller's thread, one control tick at a time.
"""

from __future__ import annotations

import logging
import math
from typing import Any

from labd.graph.graph import Side
from labd.live import Demonstration, Driving
from labd.station import Station

log = logging.getLogger("labd.scripted")
TWIST = "geometry_msgs/msg/Twist"
SPEED = 0.4  # m/s along a corridor
TURN = 3.0  # rad/s at most
ALIGNED = 0.35  # rad: turn in place beyond this heading error
GAIN = 4.0  # rad/s per rad of heading error


def move(layout: Any, pose: tuple[float, float, float]) -> tuple[float, float]:
    """The command (m/s, rad/s) toward the centre of the next cell on the shortest path."""
    x, y, yaw = pose
    path = layout.path(layout.cell_at(x, y))
    target = path[1] if len(path) > 1 else layout.goal
    tx, ty = layout.centre(target)
    error = math.remainder(math.atan2(ty - y, tx - x) - yaw, math.tau)
    turn = max(-TURN, min(TURN, GAIN * error))
    if abs(error) > ALIGNED:
        return 0.0, turn
    return SPEED * math.cos(error), turn


def demonstrate(
    station: Station,
    driving: Driving,
    *,
    user: str,
    seed: int | None = None,
    max_ticks: int = 4000,
) -> Demonstration | None:
    """Drive ``station``'s maze robot to its goal once, as ``user``; the filed drive.

    The drive starts a new episode (the robot's next seed, or ``seed``: a maze shown
    again) and ends when the episode does, or after ``max_ticks`` (then the drive is
    released, and filed as such).
    """
    robot = station.robot
    if seed is not None:  # taking the robot starts the episode of the seed after this one
        robot.sim.seed = seed - 1
    node = station.graph.create_node(f"/scripted_{user}", side=Side.CLIENT)
    try:
        command = node.advertise("/cmd_vel", TWIST)
        driving.take(node, user=user, interface="script")
        before = len(driving.filed)
        sim = robot.sim
        layout = sim.task.layout  # the maze's; other tasks have none
        for _ in range(max_ticks):
            if not sim.running:
                break
            v, w = move(layout, sim.physics.base_pose())
            command.publish({"linear": {"x": v}, "angular": {"z": w}})
            robot.step()
        if driving.current is not None and driving.current.node is node:
            driving.release(f"the script stopped at tick {sim.tick}")
        filed = driving.filed[before:]
        return filed[0] if filed else None
    finally:
        node.destroy()
