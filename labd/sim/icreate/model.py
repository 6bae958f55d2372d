"""The Create-like robot and its world as MJCF, written from primitives.

Dimensions are the iRobot Create 2's, as ROS's ``create_description`` gives them: a
disc 0.34 m across and 0.09 m tall of 3.5 kg, two driven wheels 0.072 m across on an
axle of 0.235 m, a caster front and rear (frictionless spheres, so they carry weight
without steering), and a camera on a short mast looking ahead. The frame
``base_link`` sits on the floor under the middle of the wheel axle (x forward, y
left, z up), so odometry and ``/tf`` need no height offset.

The wheels are velocity servos on their hinges, with the gear set to the wheel
radius so a control is a rim speed in m/s (the Create's ``drive direct`` command
takes the same, capped at 0.5 m/s). ``implicitfast`` integration keeps the stiff
velocity loop stable at a 5 ms step.

Geom groups, which rendering and ray casting both use: 0 the maze (floor and walls,
what blocks sight), 1 the robot as seen, 2 tags, the goal mark and the sky (seen,
never blocking), 3 the robot's collision-only wheel spheres (hidden).
"""

from __future__ import annotations

import math

import numpy as np

from labd.sim.icreate.layout import CELL, DIRECTIONS, WALL_HEIGHT, Layout
from labd.sim.icreate.tags import Tag, tag_xml

TIMESTEP = 0.002  # seconds per physics step
# A plane facing down instead of a skybox: a fifth of the cost of a camera image less,
# and invisible from above, so an overview camera still sees into the maze.
SKY_HEIGHT = 2.0
BODY_RADIUS = 0.17  # metres
BODY_HEIGHT = 0.09
BODY_CLEARANCE = 0.006  # the shell's bottom above the floor
MASS = 3.5  # kg, all of it
WHEEL_RADIUS = 0.036
WHEEL_SEPARATION = 0.235
WHEEL_MASS = 0.15
PART_MASS = 0.05  # each caster, the mast, the camera
CASTER_RADIUS = 0.015
CASTER_X = 0.13  # front and rear casters, metres from the axle
MAX_WHEEL_SPEED = 0.5  # m/s at the rim; also the top linear speed
MAX_TURN_RATE = 2 * MAX_WHEEL_SPEED / WHEEL_SEPARATION  # rad/s, turning in place
WHEEL_FORCE = 5.0  # N at the rim per wheel: up to 2.9 m/s^2, short of slipping
WHEEL_GAIN = 40.0  # N per m/s of speed error
CAMERA_POS = (0.12, 0.0, 0.2)  # in base_link
CAMERA_FOVY = 60.0  # degrees, vertical

SHELL = "shell"  # the geom whose contacts press the bumpers
CAMERA = "front"
WHEEL_JOINTS = ("left_wheel_joint", "right_wheel_joint")
WHEEL_ACTUATORS = ("left_wheel", "right_wheel")


def robot_xml(x: float = 0.0, y: float = 0.0, yaw: float = 0.0) -> str:
    """The robot's body tree, its root a free body named ``base_link`` at (x, y, yaw)."""
    shell_half = BODY_HEIGHT / 2 - BODY_CLEARANCE / 2
    shell_z = BODY_CLEARANCE + shell_half
    top = BODY_CLEARANCE + 2 * shell_half
    mast_half = (CAMERA_POS[2] - top) / 2
    body_mass = MASS - 2 * WHEEL_MASS - 4 * PART_MASS  # less casters, mast, camera
    wheels = "".join(
        f"""
      <body name="{side}_wheel_link" pos="0 {sign * WHEEL_SEPARATION / 2:g} {WHEEL_RADIUS:g}">
        <joint name="{side}_wheel_joint" type="hinge" axis="0 1 0" armature="0.0005"/>
        <geom name="{side}_wheel" type="sphere" size="{WHEEL_RADIUS:g}" mass="{WHEEL_MASS:g}"
              friction="1.0 0.005 0.0001" group="3" material="tyre"/>
        <geom name="{side}_tyre" type="cylinder" size="{WHEEL_RADIUS:g} 0.01" zaxis="0 1 0"
              contype="0" conaffinity="0" mass="0" group="1" material="tyre"/>
      </body>"""
        for side, sign in (("left", 1), ("right", -1))
    )
    casters = "".join(
        f"""
      <geom name="{name}_caster" type="sphere" size="{CASTER_RADIUS:g}" mass="{PART_MASS:g}"
            pos="{x:g} 0 {CASTER_RADIUS:g}" condim="1" priority="1" group="1"
            material="tyre"/>"""
        for name, x in (("front", CASTER_X), ("rear", -CASTER_X))
    )
    cx, cy, cz = CAMERA_POS
    return f"""
    <body name="base_link" pos="{x:g} {y:g} 0" axisangle="0 0 1 {yaw:.17g}">
      <freejoint name="base"/>
      <geom name="{SHELL}" type="cylinder" size="{BODY_RADIUS:g} {shell_half:g}"
            pos="0 0 {shell_z:g}" mass="{body_mass:g}" friction="0.2 0.005 0.0001"
            group="1" material="shell"/>
      <geom name="lid" type="cylinder" size="{BODY_RADIUS - 0.03:g} 0.002" pos="0 0 {top:g}"
            contype="0" conaffinity="0" mass="0" group="1" material="lid"/>
      <geom name="bumper" type="box" size="0.01 0.08 0.015" pos="{BODY_RADIUS - 0.005:g} 0 0.04"
            contype="0" conaffinity="0" mass="0" group="1" material="lid"/>
      {casters}
      <geom name="mast" type="cylinder" size="0.008 {mast_half:g}"
            pos="{cx - 0.03:g} 0 {top + mast_half:g}" contype="0" conaffinity="0"
            mass="{PART_MASS:g}" group="1" material="tyre"/>
      <geom name="camera_housing" type="box" size="0.015 0.03 0.015"
            pos="{cx - 0.02:g} 0 {cz:g}" contype="0" conaffinity="0" mass="{PART_MASS:g}" group="1"
            material="tyre"/>
      <camera name="{CAMERA}" pos="{cx:g} {cy:g} {cz:g}" xyaxes="0 -1 0 0 0 1"
              fovy="{CAMERA_FOVY:g}"/>
      {wheels}
    </body>"""


def actuators_xml() -> str:
    """Velocity servos on the wheels; controls are rim speeds in m/s."""
    return "".join(
        f"""
    <velocity name="{name}" joint="{joint}" gear="{WHEEL_RADIUS:g}" kv="{WHEEL_GAIN:g}"
              ctrlrange="{-MAX_WHEEL_SPEED:g} {MAX_WHEEL_SPEED:g}"
              forcerange="{-WHEEL_FORCE:g} {WHEEL_FORCE:g}"/>"""
        for name, joint in zip(WHEEL_ACTUATORS, WHEEL_JOINTS, strict=True)
    )


def world_xml(
    layout: Layout, tags: list[Tag], width: int, height: int
) -> tuple[str, dict[str, bytes]]:
    """The whole model (maze, tags, goal mark, robot) and the texture files it names.

    ``width`` x ``height`` is the camera image; the offscreen buffer is made to fit.
    """
    half_x = layout.cols * CELL / 2
    half_y = layout.rows * CELL / 2
    walls = "".join(
        f"""
    <geom name="wall{k}" type="box" pos="{b.x:g} {b.y:g} {WALL_HEIGHT / 2:g}"
          size="{b.half_x:g} {b.half_y:g} {WALL_HEIGHT / 2:g}" material="wall"/>"""
        for k, b in enumerate(layout.walls())
    )
    gx, gy = layout.centre(layout.goal)
    sx, sy = layout.centre(layout.start)
    dx, dy = DIRECTIONS[layout.heading]
    assets: dict[str, bytes] = {}
    tag_assets = []
    tag_geoms = []
    for tag in tags:
        asset, geom, files = tag_xml(tag)
        tag_assets.append(asset)
        tag_geoms.append(geom)
        assets.update(files)
    tags_xml = "".join(tag_geoms)
    xml = f"""<mujoco model="icreate-maze">
  <compiler angle="radian" autolimits="true"/>
  <option timestep="{TIMESTEP:g}" integrator="implicitfast"/>
  <visual>
    <global offwidth="{max(width, 64)}" offheight="{max(height, 64)}"/>
    <quality shadowsize="0"/>
    <map znear="0.01" zfar="50"/>
    <headlight ambient="0.45 0.45 0.45" diffuse="0.3 0.3 0.3" specular="0 0 0"/>
  </visual>
  <statistic extent="{max(half_x, half_y) * 2:g}" center="0 0 0.2"/>
  <asset>
    <texture name="floor" type="2d" builtin="checker" rgb1="0.62 0.6 0.56"
             rgb2="0.52 0.5 0.46" width="64" height="64"/>
    <material name="floor" texture="floor" texuniform="true"
              texrepeat="{1 / (2 * CELL):g} {1 / (2 * CELL):g}"/>
    <material name="wall" rgba="0.78 0.8 0.84 1"/>
    <material name="sky" rgba="0.5 0.6 0.75 1" emission="0.6"/>
    <material name="goal" rgba="0.1 0.75 0.2 1"/>
    <material name="shell" rgba="0.25 0.27 0.3 1"/>
    <material name="lid" rgba="0.55 0.57 0.6 1"/>
    <material name="tyre" rgba="0.08 0.08 0.08 1"/>{"".join(tag_assets)}
  </asset>
  <worldbody>
    <light name="sun" directional="true" pos="0 0 5" dir="0.3 0.2 -1"
           diffuse="0.5 0.5 0.5" castshadow="false"/>
    <geom name="floor" type="plane" size="{half_x:g} {half_y:g} 0.1" material="floor"/>
    <geom name="sky" type="plane" pos="0 0 {SKY_HEIGHT:g}" zaxis="0 0 -1" contype="0"
          conaffinity="0" size="{half_x + 50:g} {half_y + 50:g} {half_x + 50:g}" group="2"
          material="sky"/>{walls}
    <geom name="goal" type="box" pos="{gx:g} {gy:g} 0.0005" contype="0" conaffinity="0"
          size="{CELL * 0.45:g} {CELL * 0.45:g} 0.0005" group="2" material="goal"/>{tags_xml}
{robot_xml(sx, sy, math.atan2(dy, dx))}
  </worldbody>
  <actuator>{actuators_xml()}
  </actuator>
</mujoco>
"""
    return xml, assets


def wheel_speeds(linear: float, angular: float) -> tuple[float, float]:
    """Left and right rim speeds (m/s) for a body twist, differential-drive kinematics."""
    half = WHEEL_SEPARATION / 2
    return linear - angular * half, linear + angular * half


def yaw_quaternion(yaw: float) -> np.ndarray:
    """MuJoCo quaternion (w, x, y, z) of a rotation by ``yaw`` about z."""
    return np.array([math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)])
