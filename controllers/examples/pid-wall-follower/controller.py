"""A wall-follower for icreate-maze: the left-hand rule, steered by PID controllers.

The maze is a grid of 0.75 m cells aligned with the odometry frame, the start cell's
centre at its origin (docs/tasks.md). Keeping a hand on the left wall reaches every cell
of a maze whose walls are joined, so it reaches the goal without a plan: at each cell
centre the robot tries to turn left, else to go straight, else right, else back; a
direction it bumped into before is a wall and is not tried again from that cell.

Between cell centres two PID controllers steer: one turns the robot to the grid heading
it wants, one keeps it on the grid line (its cross-track error becomes a heading
correction), with the speed cut while the heading is off. A bump means the next cell
is wall: the robot backs up to the centre of its cell and decides again. It uses
/odom, /bumper, /cmd_vel and /lab/step only, and nothing random.
"""

from __future__ import annotations

import logging
import math
import sys

from controllers.client import EpisodeOver, Lab

CELL = 0.75
SPEED = 0.4  # m/s
ARRIVED = 0.05  # m from a centre
ALIGNED = 0.15  # rad: drive only when the heading is this close
STEPS = ((1, 0), (0, 1), (-1, 0), (0, -1))  # +x, +y, -x, -y
log = logging.getLogger("pid")


class Pid:
    """u = kp e + ki sum(e dt) + kd de/dt, the integral clamped (anti-windup)."""

    def __init__(self, kp: float, ki: float, kd: float, limit: float, dt: float) -> None:
        self.kp, self.ki, self.kd, self.limit, self.dt = kp, ki, kd, limit, dt
        self.integral = 0.0
        self.previous: float | None = None

    def reset(self) -> None:
        self.integral, self.previous = 0.0, None

    def __call__(self, error: float) -> float:
        self.integral = max(-1.0, min(1.0, self.integral + error * self.dt))
        derivative = 0.0 if self.previous is None else (error - self.previous) / self.dt
        self.previous = error
        u = self.kp * error + self.ki * self.integral + self.kd * derivative
        return max(-self.limit, min(self.limit, u))


def wrap(angle: float) -> float:
    return math.remainder(angle, math.tau)


class Follower:
    def __init__(self, dt: float) -> None:
        self.heading_pid = Pid(5.0, 0.2, 0.1, 3.0, dt)
        self.track_pid = Pid(2.5, 0.0, 0.2, 0.6, dt)
        self.walls: set[tuple[tuple[int, int], int]] = set()  # (cell, direction) bumped
        self.cell = (0, 0)
        self.facing = 0  # the direction it entered its cell in
        self.direction = 0  # the direction it tries now
        self.target: tuple[int, int] | None = None
        self.backing = False
        self.driving = False  # the last command drove forward (a bump then is a wall ahead)

    def decide(self) -> None:
        for turn in (1, 0, -1, 2):  # left hand on the wall, as it entered the cell
            d = (self.facing + turn) % 4
            if (self.cell, d) not in self.walls:
                self.direction = d
                break
        dx, dy = STEPS[self.direction]
        self.target = (self.cell[0] + dx, self.cell[1] + dy)
        self.heading_pid.reset()
        self.track_pid.reset()

    def command(self, x: float, y: float, yaw: float, bumped: bool) -> tuple[float, float]:
        v, w = self._command(x, y, yaw, bumped)
        self.driving = v > 0
        return v, w

    def _command(self, x: float, y: float, yaw: float, bumped: bool) -> tuple[float, float]:
        if bumped and self.driving and not self.backing and self.target is not None:
            self.walls.add((self.cell, self.direction))
            self.backing = True
        goal = self.cell if self.backing else self.target
        if goal is None:
            self.decide()
            goal = self.target
        assert goal is not None
        gx, gy = goal[0] * CELL, goal[1] * CELL
        dx, dy = STEPS[self.direction]
        along = (gx - x) * dx + (gy - y) * dy  # metres to go along the grid line
        across = (gy - y) * dx - (gx - x) * dy  # metres off it, to the left positive
        if self.backing:
            if along >= -ARRIVED:
                self.backing = False
                self.decide()
                return 0.0, 0.0
            error = wrap(self.direction * math.pi / 2 - yaw)
            return -0.2, self.heading_pid(error)
        if along < ARRIVED:  # arrived at the next cell's centre
            self.cell = goal
            self.facing = self.direction
            self.decide()
            return 0.0, 0.0
        want = self.direction * math.pi / 2 + self.track_pid(across)
        error = wrap(want - yaw)
        turn = self.heading_pid(error)
        if abs(error) > ALIGNED:
            return 0.0, turn
        return min(SPEED, 0.3 + along) * math.cos(error), turn


def main() -> int:
    logging.basicConfig(level=logging.INFO, format="%(name)s: %(message)s")
    with Lab.connect() as lab:
        odom = lab.subscribe("/odom", "nav_msgs/msg/Odometry")
        bumper = lab.subscribe("/bumper", "lab_msgs/msg/Bumper")
        odom.get()
        bumper.get()
        follower = Follower(dt=0.1)
        try:
            while True:
                pose = odom.get()["pose"]["pose"]
                q = pose["orientation"]
                yaw = math.atan2(
                    2 * (q["w"] * q["z"] + q["x"] * q["y"]), 1 - 2 * (q["y"] ** 2 + q["z"] ** 2)
                )
                pressed = bumper.get()
                bumped = pressed["left"] or pressed["right"]
                v, w = follower.command(pose["position"]["x"], pose["position"]["y"], yaw, bumped)
                lab.publish(
                    "/cmd_vel", "geometry_msgs/msg/Twist", {"linear": {"x": v}, "angular": {"z": w}}
                )
                lab.step()
        except EpisodeOver as end:
            log.info("%s: %s", end.status, end.reason)
    return 0


if __name__ == "__main__":
    sys.exit(main())
