"""The maze as geometry: cells, walls, start, goal, tag faces, and distances along it.

``labmaze`` draws the maze as a text grid (``*`` a wall cell, anything else floor).
Each grid cell becomes a square of ``CELL`` metres; the grid is centred on the world
origin with row 0 at the north edge (+y) and column 0 at the west edge (-x), so the
text reads like a map with north up. Wall cells become boxes, merged along runs to
keep the model small. Everything here is plain numpy and derives from the seed alone,
so a layout can be tested without building a physics.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import labmaze
import numpy as np

CELL = 0.75  # metres per grid cell
WALL_HEIGHT = 0.5  # metres; above the camera, so corridors are seen one at a time
# The four neighbours of a cell, as (row step, column step), and the world direction
# (unit x, y) each step goes: a row step of +1 goes south.
STEPS = ((-1, 0), (0, 1), (1, 0), (0, -1))  # north, east, south, west
DIRECTIONS = ((0.0, 1.0), (1.0, 0.0), (0.0, -1.0), (-1.0, 0.0))

Cell = tuple[int, int]


@dataclass(frozen=True)
class Box:
    """A wall box: centre and half-sizes in the world frame (metres)."""

    x: float
    y: float
    half_x: float
    half_y: float


@dataclass(frozen=True)
class Face:
    """The face of a wall cell that looks onto a floor cell: where a tag can hang.

    ``x, y``: the face's centre on the floor plane; ``normal``: which of ``DIRECTIONS``
    points out of the wall, into the floor cell ``cell``.
    """

    wall: Cell
    cell: Cell
    normal: int
    x: float
    y: float


class Layout:
    """One maze, its start and goal, and the distance of every cell to the goal."""

    def __init__(self, grid: np.ndarray, start: Cell, goal: Cell, heading: int) -> None:
        self.grid = grid  # bool, True for floor
        self.rows, self.cols = grid.shape
        self.start = start
        self.goal = goal
        self.heading = heading  # index into DIRECTIONS the robot faces at the start
        self.steps_to_goal = distances(grid, goal)  # -1 where unreachable or a wall

    @classmethod
    def generate(cls, size: int, rooms: int, rng: np.random.Generator) -> Layout:
        """A labmaze maze of ``size`` x ``size`` cells, the start drawn from ``rng``.

        The goal is the floor cell farthest from the start along the corridors (the
        first in row-major order on ties); the robot starts facing an open neighbour.
        """
        maze = labmaze.RandomMaze(
            height=size,
            width=size,
            max_rooms=rooms,
            room_min_size=3,
            room_max_size=3,
            simplify=False,  # True fills every dead end: corridors without choices
            random_seed=int(rng.integers(2**31 - 1)),
        )
        grid = np.array(maze.entity_layer) != "*"
        floor = [(int(i), int(j)) for i, j in zip(*np.nonzero(grid), strict=True)]
        start = floor[int(rng.integers(len(floor)))]
        from_start = distances(grid, start)
        goal_flat = int(np.argmax(from_start))
        goal = (goal_flat // grid.shape[1], goal_flat % grid.shape[1])
        open_sides = [k for k, (di, dj) in enumerate(STEPS) if grid[start[0] + di, start[1] + dj]]
        heading = open_sides[int(rng.integers(len(open_sides)))]
        return cls(grid, start, goal, heading)

    # -- geometry --------------------------------------------------------------------

    def centre(self, cell: Cell) -> tuple[float, float]:
        """World x, y of a cell's centre."""
        i, j = cell
        return (j - (self.cols - 1) / 2) * CELL, ((self.rows - 1) / 2 - i) * CELL

    def cell_at(self, x: float, y: float) -> Cell:
        """The grid cell that holds world point (x, y) (clamped to the grid)."""
        j = int(np.floor(x / CELL + self.cols / 2))
        i = int(np.floor(self.rows / 2 - y / CELL))
        return min(max(i, 0), self.rows - 1), min(max(j, 0), self.cols - 1)

    def walls(self) -> list[Box]:
        """Wall cells as boxes: horizontal runs first, then vertical runs of what is left."""
        wall = ~self.grid
        covered = np.zeros_like(wall)
        boxes: list[Box] = []
        for i in range(self.rows):
            for j0, j1 in _runs(wall[i]):
                if j1 - j0 >= 2:
                    covered[i, j0:j1] = True
                    boxes.append(self._box(i, i + 1, j0, j1))
        for j in range(self.cols):
            for i0, i1 in _runs(wall[:, j] & ~covered[:, j]):
                boxes.append(self._box(i0, i1, j, j + 1))
        return boxes

    def _box(self, i0: int, i1: int, j0: int, j1: int) -> Box:
        """The box over rows i0..i1-1 and columns j0..j1-1."""
        x0, y0 = self.centre((i0, j0))
        x1, y1 = self.centre((i1 - 1, j1 - 1))
        return Box((x0 + x1) / 2, (y0 + y1) / 2, (j1 - j0) * CELL / 2, (i1 - i0) * CELL / 2)

    def faces(self) -> list[Face]:
        """Every wall face that looks onto a floor cell, in row-major order."""
        out: list[Face] = []
        for i in range(self.rows):
            for j in range(self.cols):
                if self.grid[i, j]:
                    continue
                for k, (di, dj) in enumerate(STEPS):
                    a, b = i + di, j + dj
                    if 0 <= a < self.rows and 0 <= b < self.cols and self.grid[a, b]:
                        cx, cy = self.centre((i, j))
                        dx, dy = DIRECTIONS[k]
                        out.append(Face((i, j), (a, b), k, cx + dx * CELL / 2, cy + dy * CELL / 2))
        return out

    # -- distances -------------------------------------------------------------------

    def path(self, cell: Cell) -> list[Cell]:
        """The shortest path of cells from ``cell`` to the goal (both included)."""
        if self.steps_to_goal[cell] < 0:
            return []
        out = [cell]
        while out[-1] != self.goal:
            out.append(self._downhill(out[-1]))
        return out

    def _downhill(self, cell: Cell) -> Cell:
        """The first neighbour (N, E, S, W) one step closer to the goal."""
        here = self.steps_to_goal[cell]
        for di, dj in STEPS:
            nxt = (cell[0] + di, cell[1] + dj)
            if self.steps_to_goal[nxt] == here - 1:
                return nxt
        raise AssertionError(f"no way down from {cell}")

    def distance_to_goal(self, x: float, y: float) -> float:
        """Metres from (x, y) to the goal's centre along the corridors.

        In the goal cell, the straight distance; elsewhere the straight distance to
        the centre of the next cell on the shortest path plus that cell's path length.
        Continuous along straight corridors, so its decrease is a fair measure of
        progress.
        """
        cell = self.cell_at(x, y)
        steps = int(self.steps_to_goal[cell])
        if steps < 0:  # inside a wall (pushed into it): measure from the nearest floor
            return float(self.steps_to_goal.max() + 1) * CELL
        target = cell if steps == 0 else self._downhill(cell)
        tx, ty = self.centre(target)
        return max(steps - 1, 0) * CELL + float(np.hypot(x - tx, y - ty))

    def text(self) -> str:
        """The maze as text: ``*`` wall, ``S`` start, ``G`` goal, space floor."""
        rows = []
        for i in range(self.rows):
            row = ""
            for j in range(self.cols):
                cell = (i, j)
                floor = "S" if cell == self.start else "G" if cell == self.goal else " "
                row += floor if self.grid[cell] else "*"
            rows.append(row)
        return "\n".join(rows)


def distances(grid: np.ndarray, origin: Cell) -> np.ndarray:
    """Steps from ``origin`` to every floor cell, 4-connected (-1: unreachable or wall)."""
    out = np.full(grid.shape, -1, dtype=np.int64)
    out[origin] = 0
    queue = deque([origin])
    while queue:
        i, j = queue.popleft()
        for di, dj in STEPS:
            a, b = i + di, j + dj
            if 0 <= a < grid.shape[0] and 0 <= b < grid.shape[1] and grid[a, b] and out[a, b] < 0:
                out[a, b] = out[i, j] + 1
                queue.append((a, b))
    return out


def _runs(line: np.ndarray) -> list[tuple[int, int]]:
    """Maximal runs of True as half-open (start, end) index pairs."""
    out = []
    start = -1
    for k, value in enumerate([*line.tolist(), False]):
        if value and start < 0:
            start = k
        elif not value and start >= 0:
            out.append((start, k))
            start = -1
    return out
