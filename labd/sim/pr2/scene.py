"""The table, the objects on it and the target area, laid out from the seed.

The robot starts at the origin of ``odom`` facing +x; the table stands in front of
it. Objects (boxes and cylinders, each its own colour) and the target area are
placed in the part of the table the arms reach without driving, never overlapping
each other or the area, with room between them for an open gripper's fingers.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from labd.sim.pr2 import model

# The table: its top's centre, half extents along x and y, top height and thickness.
TABLE_CENTER = (0.72, 0.0)
TABLE_HALF = (0.3, 0.6)
TABLE_TOP = 0.72
TABLE_THICKNESS = 0.04
# Where object and area centres may be (odom, m): within the arms' reach from the start.
PLACE_X = (0.5, 0.72)
PLACE_Y = (-0.3, 0.3)
AREA_HALF = 0.08  # the target area is a square 0.16 m across
CLEARANCE = 0.05  # between objects' bounding circles, for the fingers
AREA_CLEARANCE = 0.02  # between an object's bounding circle and the area
PLACEMENT_TRIES = 200  # places tried for one object before the whole layout is redrawn

COLOURS = {
    "red": "0.85 0.15 0.15 1",
    "green": "0.15 0.7 0.2 1",
    "blue": "0.15 0.3 0.9 1",
    "yellow": "0.95 0.85 0.1 1",
    "orange": "0.95 0.5 0.05 1",
    "purple": "0.55 0.2 0.75 1",
}
SHAPES = ("box", "cylinder")
MAX_OBJECTS = len(COLOURS)


@dataclass(frozen=True)
class Thing:
    """One object on the table.

    ``size`` is the full extent (m) along the object's own x, y and z; a cylinder's x
    and y are its diameter. ``x``, ``y`` and ``yaw`` place it upright on the table.
    """

    name: str
    shape: str
    colour: str
    size: tuple[float, float, float]
    mass: float
    x: float
    y: float
    yaw: float

    @property
    def radius(self) -> float:
        """Half the diagonal of its footprint: no part of it reaches farther."""
        return 0.5 * math.hypot(self.size[0], self.size[1])

    @property
    def rest_z(self) -> float:
        return TABLE_TOP + self.size[2] / 2


@dataclass(frozen=True)
class Layout:
    """What a seed decided: the objects, which one to move, and where to."""

    things: tuple[Thing, ...]
    target: str  # the name of the object to move
    area: tuple[float, float]  # the target area's centre (odom x, y)

    def thing(self, name: str) -> Thing:
        return next(t for t in self.things if t.name == name)


def _round(value: float) -> float:
    """Values go into the MJCF text; rounding here keeps the model and the layout equal."""
    return round(float(value), 4)


def layout(random: np.random.RandomState, count: int) -> Layout:
    """Objects, target and area drawn from ``random``; deterministic for its state."""
    while True:  # a crowded draw is drawn again (rarely, and only with many objects)
        plan = _draw(random, count)
        if plan is not None:
            return plan


def _draw(random: np.random.RandomState, count: int) -> Layout | None:
    area = (_round(random.uniform(*PLACE_X)), _round(random.uniform(*PLACE_Y)))
    colours = [str(c) for c in random.permutation(list(COLOURS))[:count]]
    things: list[Thing] = []
    for colour in colours:
        shape = SHAPES[random.randint(len(SHAPES))]
        if shape == "box":
            width, depth = random.uniform(0.04, 0.065), random.uniform(0.04, 0.065)
        else:
            width = depth = random.uniform(0.04, 0.065)
        dims = (_round(width), _round(depth), _round(random.uniform(0.06, 0.12)))
        mass = _round(random.uniform(0.1, 0.3))
        radius = 0.5 * math.hypot(dims[0], dims[1])
        for _ in range(PLACEMENT_TRIES):
            x, y = _round(random.uniform(*PLACE_X)), _round(random.uniform(*PLACE_Y))
            gap = max(abs(x - area[0]), abs(y - area[1])) - AREA_HALF
            if gap >= radius + AREA_CLEARANCE and all(
                math.hypot(x - t.x, y - t.y) >= radius + t.radius + CLEARANCE for t in things
            ):
                break
        else:
            return None
        yaw = _round(random.uniform(-math.pi, math.pi)) if shape == "box" else 0.0
        things.append(Thing(f"{colour}_{shape}", shape, colour, dims, mass, x, y, yaw))
    target = things[random.randint(len(things))].name
    return Layout(tuple(things), target, area)


def _object_xml(thing: Thing) -> str:
    sx, sy, sz = (s / 2 for s in thing.size)
    if thing.shape == "box":
        geom = f'type="box" size="{sx:g} {sy:g} {sz:g}"'
    else:
        geom = f'type="cylinder" size="{sx:g} {sz:g}"'
    return f"""
    <body name="{thing.name}" pos="{thing.x:g} {thing.y:g} {thing.rest_z:g}"
          euler="0 0 {thing.yaw:g}">
      <freejoint name="{thing.name}"/>
      <geom name="{thing.name}" class="world" {geom} mass="{thing.mass:g}"
            rgba="{COLOURS[thing.colour]}"/>
    </body>"""


def _table_xml(area: tuple[float, float]) -> str:
    cx, cy = TABLE_CENTER
    hx, hy = TABLE_HALF
    ht = TABLE_THICKNESS / 2
    legs = "".join(
        f'<geom class="world" type="box" pos="{cx + sx * (hx - 0.04):g} {cy + sy * (hy - 0.04):g}'
        f' {(TABLE_TOP - TABLE_THICKNESS) / 2:g}" size="0.025 0.025'
        f' {(TABLE_TOP - TABLE_THICKNESS) / 2:g}" rgba="0.4 0.3 0.2 1"/>'
        for sx in (-1, 1)
        for sy in (-1, 1)
    )
    return f"""
    <geom name="table" class="world" type="box" pos="{cx:g} {cy:g} {TABLE_TOP - ht:g}"
          size="{hx:g} {hy:g} {ht:g}" rgba="0.72 0.6 0.45 1"/>
    {legs}
    <geom name="target_area" class="visual" type="box"
          pos="{area[0]:g} {area[1]:g} {TABLE_TOP + 0.0005:g}"
          size="{AREA_HALF:g} {AREA_HALF:g} 0.0005" rgba="0.3 0.85 0.9 1"/>"""


def world_xml(plan: Layout, *, timestep: float, width: int, height: int) -> str:
    """The whole MJCF: options, robot, table and objects; ``width`` x ``height`` is
    the largest image the head camera renders."""
    objects = "".join(_object_xml(t) for t in plan.things)
    return f"""<mujoco model="pr2-table">
  <compiler angle="radian" autolimits="true"/>
  <option timestep="{timestep:g}" integrator="implicitfast" cone="elliptic" impratio="10"/>
  <visual>
    <global offwidth="{max(width, 640)}" offheight="{max(height, 480)}"/>
    <quality shadowsize="0"/>
    <headlight ambient="0.45 0.45 0.45" diffuse="0.5 0.5 0.5" specular="0.1 0.1 0.1"/>
  </visual>
  <default>{model.defaults()}
  </default>
  <asset>
    <texture name="grid" type="2d" builtin="checker" rgb1="0.55 0.55 0.55"
             rgb2="0.45 0.45 0.45" width="64" height="64"/>
    <material name="floor" texture="grid" texrepeat="8 8"/>
    <texture name="sky" type="skybox" builtin="gradient" rgb1="0.75 0.8 0.85" rgb2="0.35 0.4 0.45"
             width="32" height="32"/>
  </asset>
  <worldbody>
    <light pos="0.5 0 3" dir="0 0 -1" diffuse="0.5 0.5 0.5"/>
    <geom name="floor" class="world" type="plane" size="5 5 0.1" material="floor"/>
    {_table_xml(plan.area)}
    {objects}
    {model.robot_body()}
  </worldbody>
  <actuator>
    {model.actuators()}
  </actuator>
</mujoco>
"""
