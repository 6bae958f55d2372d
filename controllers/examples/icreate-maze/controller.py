"""Solve the icreate-maze task: reach the goal cell of an unknown maze.

The maze is a grid of 0.75 m cells, each floor or a solid block of wall, axis-aligned
in the odometry frame with the start cell's centre at the origin (docs/tasks.md), so
the controller keeps a map of cells (unknown, floor, wall) and plans on it:

- **Plan** the quickest way to the goal cell (from /goal) with Dijkstra over cells and
  headings: unknown cells count as floor (a little dearer than known floor), turns cost
  time too. Re-plan whenever the robot enters a cell or learns something.
- **Move** from cell centre to cell centre: turn in place toward the next cell, then
  drive along the grid line, steering back onto it, through straight runs without
  stopping; slow down before entering a cell not known to be floor.
- **Map** with the bumpers: a bump while driving into a cell means it is wall (the
  robot backs up to the cell it came from and re-plans); a cell the robot's front has
  entered without a bump is floor. And with the tags: a tag hangs on a wall face, so
  the cell behind it is wall, the one in front floor, and the camera's line of sight
  to it crosses only floor.
- **Stay localised.** Wheel odometry drifts a little. The tag detector is exact and
  tags hang at known places on the grid (centred on a cell's face, 0.2 m up), so every
  tag seen fixes the heading (its face is along a grid axis) and the position (its
  centre is on the grid's lattice of faces). A head-on bump fixes the position along
  the direction of travel (the wall's face is on a cell boundary).

It uses only /odom, /bumper, /ar_tags, /goal, /cmd_vel and /lab/step, through the
lab's client library. Everything depends on the messages only (no randomness, no
wall clock), so the same seed gives the same run.
"""

from __future__ import annotations

import heapq
import itertools
import logging
import math
import sys
from collections.abc import Iterator
from dataclasses import dataclass

from controllers.client import EpisodeOver, Lab, Message

CELL = 0.75  # m: the maze's cells
HALF = CELL / 2
RADIUS = 0.17  # m: the robot's disc
CAMERA = 0.12  # m: the camera ahead of base_link (at the tags' height)

MAX_SPEED = 0.5  # m/s
PROBE_SPEED = 0.2  # m/s when the front reaches a cell not known to be floor
TURN_SPEED = 3.0  # rad/s
BRAKE = 0.8  # m/s^2 planned deceleration (the wheels manage 2.9)
HEADING_GAIN = 5.0  # rad/s per rad of heading error
TRACK_GAIN = 2.0  # rad of heading per m off the grid line
ARRIVED = 0.03  # m from a cell's centre: close enough to turn there
ALIGNED = 0.06  # rad: close enough to the heading to drive
GIVE_UP = 10.0  # s a move may take (per cell): stuck, it re-plans from where it is

UNKNOWN_COST = 0.4  # extra cost (in cells) of planning through an unknown cell
TURN_COST = 0.6  # cost (in cells) of a quarter turn

UNKNOWN, FLOOR, WALL = 0, 1, 2
# The four headings: +x, +y, -x, -y in the grid (odom) frame.
STEPS = ((1, 0), (0, 1), (-1, 0), (0, -1))

log = logging.getLogger("maze")
Cell = tuple[int, int]


def wrap(angle: float) -> float:
    """``angle`` in [-pi, pi)."""
    return (angle + math.pi) % (2 * math.pi) - math.pi


def yaw_of(q: Message) -> float:
    """The yaw of a quaternion (rotation about z)."""
    return math.atan2(2 * (q["w"] * q["z"] + q["x"] * q["y"]), 1 - 2 * (q["y"] ** 2 + q["z"] ** 2))


def cell_of(x: float, y: float) -> Cell:
    return round(x / CELL), round(y / CELL)


@dataclass
class Pose:
    """The robot in the grid frame (odom, corrected for drift): m, m, rad."""

    x: float
    y: float
    yaw: float


class Map:
    """What is known of each cell; unknown cells are not stored."""

    def __init__(self) -> None:
        self.cells: dict[Cell, int] = {}

    def __getitem__(self, cell: Cell) -> int:
        return self.cells.get(cell, UNKNOWN)

    def mark(self, cell: Cell, state: int) -> bool:
        """Record ``state``; whether it is news."""
        if self.cells.get(cell) == state:
            return False
        self.cells[cell] = state
        return True

    def cost(self, cell: Cell) -> float:
        """The cost of stepping into ``cell`` (which is not known to be wall)."""
        if self[cell] == FLOOR:
            return 1.0
        return 1.0 + UNKNOWN_COST

    def plan(self, start: Cell, heading: int, goal: Cell) -> list[Cell]:
        """The cheapest cells from ``start`` (facing ``heading``) to ``goal``, both included.

        Dijkstra over (cell, heading): a step forward costs ``cost``, a quarter turn
        TURN_COST. Walls are never entered, and the search stays within a margin of
        the known cells, since the maze is finite. An empty list: no way.
        """
        known = [*self.cells, start, goal]
        lo_x = min(c[0] for c in known) - 2
        hi_x = max(c[0] for c in known) + 2
        lo_y = min(c[1] for c in known) - 2
        hi_y = max(c[1] for c in known) + 2
        best: dict[tuple[Cell, int], float] = {(start, heading): 0.0}
        parent: dict[tuple[Cell, int], tuple[Cell, int]] = {}
        queue: list[tuple[float, Cell, int]] = [(0.0, start, heading)]
        while queue:
            cost, cell, facing = heapq.heappop(queue)
            if cost > best[(cell, facing)]:
                continue
            if cell == goal:
                path = [cell]
                state = (cell, facing)
                while state in parent:
                    state = parent[state]
                    if state[0] != path[-1]:
                        path.append(state[0])
                return path[::-1]
            dx, dy = STEPS[facing]
            ahead = (cell[0] + dx, cell[1] + dy)
            moves = [((ahead, facing), self.cost(ahead))]
            moves += [((cell, (facing + turn) % 4), TURN_COST) for turn in (1, 3)]
            for state, step_cost in moves:
                (x, y), _ = state
                if self[state[0]] == WALL or not (lo_x <= x <= hi_x and lo_y <= y <= hi_y):
                    continue
                if cost + step_cost < best.get(state, math.inf):
                    best[state] = cost + step_cost
                    parent[state] = (cell, facing)
                    heapq.heappush(queue, (cost + step_cost, state[0], state[1]))
        return []


class MazeSolver:
    """Drives the robot to the goal cell; ``run`` ends with the episode (EpisodeOver)."""

    def __init__(self, lab: Lab) -> None:
        self.lab = lab
        self.odom = lab.subscribe("/odom", "nav_msgs/msg/Odometry")
        self.bumper = lab.subscribe("/bumper", "lab_msgs/msg/Bumper")
        self.tags = lab.subscribe("/ar_tags", "lab_msgs/msg/ArTagArray")
        goal = lab.subscribe("/goal", "geometry_msgs/msg/PointStamped").get()["point"]
        self.goal = cell_of(goal["x"], goal["y"])
        self.map = Map()
        self.pose = Pose(0.0, 0.0, 0.0)
        self.last_odom = self._odom_pose()
        self.bumped = self.head_on = False
        self.news = False  # the map changed since the last plan
        self.time = 0.0
        self.map.mark((0, 0), FLOOR)
        self.map.mark((1, 0), FLOOR)  # the robot starts facing an open neighbour (+x)
        self.map.mark(self.goal, FLOOR)

    # -- sensing -----------------------------------------------------------------------

    def _odom_pose(self) -> tuple[float, float, float]:
        pose = self.odom.get()["pose"]["pose"]
        return pose["position"]["x"], pose["position"]["y"], yaw_of(pose["orientation"])

    def speed(self) -> float:
        """The forward speed (m/s) odometry measured at the end of the last tick."""
        return float(self.odom.get()["twist"]["twist"]["linear"]["x"])

    def tick(self, speed: float, turn: float) -> None:
        """Command the base for one control tick, step, and take in what it saw."""
        twist = {"linear": {"x": speed}, "angular": {"z": turn}}
        self.lab.publish("/cmd_vel", "geometry_msgs/msg/Twist", twist)
        self.time = self.lab.step().time
        # Dead reckoning: this tick's motion in the robot's frame, applied to the pose.
        x0, y0, yaw0 = self.last_odom
        x1, y1, yaw1 = self.last_odom = self._odom_pose()
        c, s = math.cos(yaw0), math.sin(yaw0)
        forward, left = c * (x1 - x0) + s * (y1 - y0), -s * (x1 - x0) + c * (y1 - y0)
        p = self.pose
        c, s = math.cos(p.yaw), math.sin(p.yaw)
        p.x += c * forward - s * left
        p.y += s * forward + c * left
        p.yaw = wrap(p.yaw + wrap(yaw1 - yaw0))
        bumper = self.bumper.get()
        self.bumped = bool(bumper["left"] or bumper["right"])
        self.head_on = bool(bumper["left"] and bumper["right"])
        for tag in self.tags.get()["tags"]:
            self._see_tag(tag)

    def _see_tag(self, tag: Message) -> None:
        """Correct the pose with a tag, and map its wall and the free line of sight."""
        position, orientation = tag["pose"]["position"], tag["pose"]["orientation"]
        # Into the wall (the tag's z) and the tag's centre, in base_link (optical z
        # forward, x right, y down).
        qx, qy, qz, qw = (orientation[k] for k in "xyzw")
        into_forward = 1 - 2 * (qx * qx + qy * qy)  # R[2][2]
        into_left = -2 * (qx * qz + qw * qy)  # -R[0][2]
        bearing = math.atan2(into_left, into_forward)
        forward, left = CAMERA + position["z"], -position["x"]
        # The face's normal is along a grid axis: snap it, which fixes the heading.
        p = self.pose
        axis = round((p.yaw + bearing) / (math.pi / 2))
        yaw = wrap(axis * math.pi / 2 - bearing)
        if abs(wrap(yaw - p.yaw)) > 0.3:
            log.warning("%.1f s: ignored tag %d: heading off by too much", self.time, tag["id"])
            return
        c, s = math.cos(yaw), math.sin(yaw)
        tx, ty = p.x + c * forward - s * left, p.y + s * forward + c * left
        # The tag is centred on a face: on a cell boundary across the axis, at a cell's
        # centre along the face.
        nx, ny = STEPS[axis % 4]
        if nx:
            true_x, true_y = (math.floor(tx / CELL) + 0.5) * CELL, round(ty / CELL) * CELL
        else:
            true_x, true_y = round(tx / CELL) * CELL, (math.floor(ty / CELL) + 0.5) * CELL
        p.x, p.y, p.yaw = p.x + true_x - tx, p.y + true_y - ty, yaw
        self._learn(cell_of(true_x + nx * HALF, true_y + ny * HALF), WALL)
        self._learn(cell_of(true_x - nx * HALF, true_y - ny * HALF), FLOOR)
        # The line of sight from the camera crosses floor only; skip points near edges.
        cx, cy = p.x + c * CAMERA, p.y + s * CAMERA
        length = math.hypot(true_x - cx, true_y - cy)
        for k in range(int(length / 0.05)):
            f = k * 0.05 / length
            x, y = cx + f * (true_x - cx), cy + f * (true_y - cy)
            u, v = x / CELL - round(x / CELL), y / CELL - round(y / CELL)
            if max(abs(u), abs(v)) < 0.5 - 0.08 / CELL:
                self._learn(cell_of(x, y), FLOOR)

    def _learn(self, cell: Cell, state: int) -> None:
        if self.map.mark(cell, state):
            self.news = True

    # -- moving ------------------------------------------------------------------------

    def cell(self) -> Cell:
        return cell_of(self.pose.x, self.pose.y)

    def heading(self) -> int:
        return round(self.pose.yaw / (math.pi / 2)) % 4

    def turn_to(self, heading: int) -> None:
        """Turn in place until facing ``heading`` (an index of STEPS)."""
        target = heading * math.pi / 2
        deadline = self.time + GIVE_UP
        while self.time < deadline:
            error = wrap(target - self.pose.yaw)
            if abs(error) < ALIGNED:
                return
            self.tick(0.0, max(-TURN_SPEED, min(TURN_SPEED, HEADING_GAIN * error)))

    def drive(self, heading: int, start: Cell, cells: int) -> None:
        """Drive from ``start``'s centre along ``heading``, aiming ``cells`` ahead.

        On entering each cell it re-plans: the run is stretched or cut short (to stop
        at a centre, where it can turn). A bump marks the cell ahead as wall and backs
        the robot up to the centre of the cell it came from.
        """
        dx, dy = STEPS[heading]
        target = cells
        entered = 0  # the furthest cell along the run the robot's centre has entered
        deadline = self.time + GIVE_UP * (cells + 1)
        while self.time < deadline:
            p = self.pose
            along = (p.x - start[0] * CELL) * dx + (p.y - start[1] * CELL) * dy
            across = -(p.x - start[0] * CELL) * dy + (p.y - start[1] * CELL) * dx
            if self.bumped:
                self._bump(heading, start, along)
                return
            front = along + RADIUS
            for k in range(entered + 1, target + 1):  # cells the front has entered: floor
                if front > k * CELL - HALF + 0.03:
                    self._learn((start[0] + k * dx, start[1] + k * dy), FLOOR)
            here = round(along / CELL)
            if here > entered and along > here * CELL - HALF + 0.05:
                entered = here
                target = entered + self._straight(heading)
            elif self.news:  # a tag showed something: does the run still hold?
                target = entered + self._straight(heading)
            remaining = target * CELL - along
            if abs(remaining) < ARRIVED and abs(self.speed()) < 0.05:
                return
            speed = min(MAX_SPEED, math.sqrt(2 * BRAKE * abs(remaining)), 2.5 * abs(remaining))
            speed = math.copysign(speed, remaining)
            ahead = (start[0] + (entered + 1) * dx, start[1] + (entered + 1) * dy)
            to_touch = (entered + 1) * CELL - HALF - front
            if self.map[ahead] != FLOOR and entered < target:
                # Reach the unknown cell at probing speed.
                limit = math.sqrt(PROBE_SPEED**2 + 2 * BRAKE * max(0.0, to_touch - 0.05))
                speed = min(speed, limit)
            desired = heading * math.pi / 2 - max(-0.4, min(0.4, TRACK_GAIN * across))
            error = wrap(desired - p.yaw)
            speed *= max(0.0, math.cos(error))
            self.tick(speed, max(-TURN_SPEED, min(TURN_SPEED, HEADING_GAIN * error)))

    def _straight(self, heading: int) -> int:
        """How many cells the current plan goes straight on along ``heading`` from here."""
        return len(list(_run(self.plan(), STEPS[heading])))

    def _bump(self, heading: int, start: Cell, along: float) -> None:
        """The front touched a wall: map it, fix the position, back up to a centre."""
        dx, dy = STEPS[heading]
        k = round((along + RADIUS + HALF) / CELL)  # the cell whose near face was touched
        wall = (start[0] + k * dx, start[1] + k * dy)
        self._learn(wall, WALL)
        if self.head_on:  # the front is on the face: the position along the run is known
            shift = (k * CELL - HALF - RADIUS) - along
            self.pose.x += shift * dx
            self.pose.y += shift * dy
        log.info("%.1f s: bumped into %s", self.time, wall)
        back = (start[0] + (k - 1) * dx, start[1] + (k - 1) * dy)
        self.back_to(back, heading)

    def back_to(self, cell: Cell, heading: int) -> None:
        """Reverse along ``heading``'s line to ``cell``'s centre."""
        dx, dy = STEPS[heading]
        deadline = self.time + GIVE_UP
        while self.time < deadline:
            p = self.pose
            remaining = (cell[0] * CELL - p.x) * dx + (cell[1] * CELL - p.y) * dy
            across = -(p.x - cell[0] * CELL) * dy + (p.y - cell[1] * CELL) * dx
            if abs(remaining) < ARRIVED and abs(self.speed()) < 0.05:
                return
            speed = min(MAX_SPEED, math.sqrt(2 * BRAKE * abs(remaining)), 2.5 * abs(remaining))
            # Reversing, steer the back onto the line: the sign of the correction flips.
            desired = heading * math.pi / 2 + max(-0.4, min(0.4, TRACK_GAIN * across))
            error = wrap(desired - p.yaw)
            self.tick(math.copysign(speed, remaining), HEADING_GAIN * error)

    def plan(self) -> list[Cell]:
        """The way from here to the goal on the map (two cells at least)."""
        self.news = False
        path = self.map.plan(self.cell(), self.heading(), self.goal)
        if len(path) < 2:
            # Walls all round: something was mapped wrong. Keep only the floor, retry.
            log.warning("%.1f s: no way to the goal; forgetting the walls", self.time)
            self.map.cells = {c: v for c, v in self.map.cells.items() if v == FLOOR}
            path = self.map.plan(self.cell(), self.heading(), self.goal)
        return path

    def run(self) -> None:
        """Plan, turn, drive; again and again until the episode ends (EpisodeOver)."""
        while True:
            here = self.cell()
            path = self.plan()
            step = (path[1][0] - here[0], path[1][1] - here[1])
            heading = STEPS.index(step)
            log.info(
                "%.1f s: at %s, heading for %s, %d cells to go",
                self.time,
                here,
                path[1],
                len(path) - 1,
            )
            run = list(_run(path, step))
            facing = self.heading()
            if heading == (facing + 2) % 4 and all(self.map[c] == FLOOR for c in run):
                self.back_to(run[-1], facing)  # known floor behind: reverse, no U-turn
            else:
                self.turn_to(heading)
                self.drive(heading, here, len(run))


def _run(path: list[Cell], step: Cell) -> Iterator[Cell]:
    """The cells of ``path`` reached by going straight along ``step`` from its start."""
    for a, b in itertools.pairwise(path):
        if (b[0] - a[0], b[1] - a[1]) != step:
            return
        yield b


def main() -> int:
    logging.basicConfig(level=logging.INFO, format="%(name)s: %(message)s", stream=sys.stdout)
    with Lab.connect() as lab:
        solver = MazeSolver(lab)
        log.info("goal cell %s", solver.goal)
        try:
            solver.run()
        except EpisodeOver as over:
            log.info("episode over at %.1f s: %s", over.tick.time, over.tick.message)
    return 0


if __name__ == "__main__":
    sys.exit(main())
