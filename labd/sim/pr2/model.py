"""The PR2-like robot as MJCF, built from primitives with the real robot's dimensions.

Dimensions, joint names, limits and speeds are those of ``pr2_description`` (the
ROS package that describes the PR2): a 0.668 m square base, a torso that lifts
0.31 m, shoulders 0.188 m either side of it, an upper arm of 0.4 m and a forearm
of 0.321 m, a tool frame 0.18 m past the wrist, grippers that open to 0.09 m and a
pan-tilt head. Shapes are boxes, cylinders and capsules; masses are close to the
real links'. What differs, and why:

- the base is a planar joint (x, y, yaw) driven by velocity actuators instead of
  four steered casters: it moves as the PR2's base controller makes it move;
- each gripper is two parallel sliding fingers (the real ones pivot), so the
  opening is exactly the commanded gap;
- the arms are gravity-compensated (``gravcomp``), as the real arms are by their
  counterbalance springs, so position servos hold them without sagging;
- the continuous roll joints are limited to one turn either way, and the torso
  moves at 0.05 m/s (the real one at 0.013 m/s), so that a trial need not wait.

Robot geoms collide with the world (table, objects, floor) but not with each other.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

SIDES = ("l", "r")

BASE_HALF = 0.334  # the base is 0.668 m square
BASE_LINK_Z = 0.051  # base_link above base_footprint
TORSO_ORIGIN = (-0.05, 0.0, BASE_LINK_Z + 0.739675)  # torso_lift_link at its lowest
HEAD_PAN_ORIGIN = (-0.01707, 0.0, 0.38145)  # in torso_lift_link
HEAD_TILT_OFFSET = 0.068
CAMERA_OFFSET = (0.1, 0.0, 0.0645)  # the camera's lens in head_tilt_link
CAMERA_FOVY = 60.0  # degrees, vertical (75 degrees across at 4:3)
SHOULDER_Y = 0.188
SHOULDER_LIFT_OFFSET = 0.1
UPPER_ARM = 0.4
FOREARM = 0.321
TOOL = 0.18  # wrist roll axis to the tool frame, between the fingertips
GRIPPER_MAX = 0.09  # widest opening, m

CAMERA = "head"  # the MJCF camera
CAMERA_BODY = "head_tilt_link"


@dataclass(frozen=True)
class Joint:
    """A commanded joint: its limits and how its position servo behaves.

    ``velocity`` bounds how fast the lab moves the joint's setpoint (rad/s or m/s);
    ``kp``, ``kv`` and ``force`` are the servo's gains and its force limit.
    """

    name: str
    low: float
    high: float
    velocity: float
    kp: float
    kv: float
    force: float
    continuous: bool = False  # turns without end on the real robot


ROLL = 2 * math.pi  # continuous joints are limited to one turn either way


def arm_joints(side: str) -> tuple[Joint, ...]:
    """The seven joints of arm ``side`` ("l" or "r"), shoulder to wrist."""
    s = 1.0 if side == "l" else -1.0
    pan = sorted((s * math.pi / 4 - 1.5, s * math.pi / 4 + 1.5))
    roll = sorted((s * 1.55 - 2.35, s * 1.55 + 2.35))
    return (
        Joint(f"{side}_shoulder_pan_joint", pan[0], pan[1], 2.088, 600.0, 80.0, 150.0),
        Joint(f"{side}_shoulder_lift_joint", -0.5236, 1.3963, 2.082, 600.0, 80.0, 150.0),
        Joint(f"{side}_upper_arm_roll_joint", roll[0], roll[1], 3.27, 200.0, 20.0, 60.0),
        Joint(f"{side}_elbow_flex_joint", -2.3213, 0.0, 3.3, 200.0, 20.0, 60.0),
        Joint(f"{side}_forearm_roll_joint", -ROLL, ROLL, 3.6, 30.0, 3.0, 15.0, True),
        Joint(f"{side}_wrist_flex_joint", -2.094, 0.0, 3.078, 30.0, 3.0, 15.0),
        Joint(f"{side}_wrist_roll_joint", -ROLL, ROLL, 3.6, 10.0, 1.0, 10.0, True),
    )


TORSO = Joint("torso_lift_joint", 0.0, 0.31, 0.05, 50000.0, 5000.0, 10000.0)
HEAD = (
    Joint("head_pan_joint", -3.007, 3.007, 6.0, 50.0, 6.0, 20.0),
    Joint("head_tilt_joint", -0.471238, 1.39626, 5.0, 50.0, 5.0, 20.0),
)
ARMS = {side: arm_joints(side) for side in SIDES}
# The gap between the fingers, m: a virtual joint, as on the PR2 (l_gripper_joint). Its
# servo gains are unused: each finger has its own servo (FINGER_*), given half the gap.
GRIPPER = {side: Joint(f"{side}_gripper_joint", 0.0, GRIPPER_MAX, 0.2, 0, 0, 0) for side in SIDES}
FINGER_KP, FINGER_KV, FINGER_FORCE = 1000.0, 30.0, 40.0  # each finger's servo, N/m, N s/m, N

# The base's speed limits in its own frame (the PR2 base controller's 0.5 m/s).
BASE_LINEAR_MAX = 0.5  # m/s, the length of (linear.x, linear.y)
BASE_ANGULAR_MAX = 1.0  # rad/s
BASE_JOINTS = ("base_x_joint", "base_y_joint", "base_yaw_joint")
# Per base joint: actuator name, velocity gain (N s/m, N m s), stiffness of the hold on
# the integrated command (N/m, N m/rad), force limit (N, N m). The hold's target is kept
# within BASE_HOLD_SLACK of the base, so pushing against a wall does not wind it up.
BASE_SERVOS = (
    ("base_x", 5000.0, 20000.0, 2000.0),
    ("base_y", 5000.0, 20000.0, 2000.0),
    ("base_yaw", 600.0, 3000.0, 600.0),
)
BASE_HOLD_SLACK = 0.05  # m, rad

# Arms tucked in front of the torso (the PR2's tuck_arms pose) and the head on the table.
TUCKED = {
    "l": (0.06024, 1.248526, 1.789070, -1.683386, -1.7343417, -0.0962141, -0.0864407),
    "r": (-0.023593, 1.1072800, -1.5566882, -2.124408, -1.4175, -1.8417, 0.21436),
}
# Arms ready over the table's front edge, elbows out, grippers pointing down (tool y
# along odom y on the left, -y on the right): with the torso at 0.2 m the tool frames
# are at (0.5, +-0.22, 0.95) in base_footprint. The arm IK leans toward this pose.
READY = {
    "l": (0.66, -0.18, 1.34, -1.65, 1.37, -1.78, 2.1),
    "r": (-0.66, -0.18, -1.34, -1.65, -1.37, -1.78, 1.04),
}
HEAD_START = (0.0, 0.75)  # pan, tilt: looking down at the table

BLUE, GREY, WHITE, DARK = (
    "0.25 0.35 0.6 1",
    "0.55 0.55 0.58 1",
    "0.85 0.85 0.85 1",
    "0.2 0.2 0.22 1",
)


def defaults() -> str:
    """MJCF <default> classes: robot links, finger pads, the world, decoration."""
    return """
    <default class="robot">
      <joint armature="0.05" damping="0.5"/>
      <geom contype="2" conaffinity="1" group="1" condim="3" friction="1 0.005 0.0001"/>
      <default class="pad">
        <geom condim="4" friction="1.5 0.02 0.0001" solref="0.005 1" rgba="0.15 0.15 0.15 1"/>
      </default>
      <default class="decor">
        <geom contype="0" conaffinity="0" group="2"/>
      </default>
    </default>
    <default class="world">
      <geom contype="1" conaffinity="3" group="0" condim="3" friction="1 0.005 0.0001"/>
    </default>
    <default class="visual">
      <geom contype="0" conaffinity="0" group="2"/>
    </default>"""


def _hinge(joint: Joint, axis: str) -> str:
    limit = "" if joint.continuous else f' range="{joint.low:.6g} {joint.high:.6g}"'
    return f'<joint name="{joint.name}" axis="{axis}"{limit}/>'


def _arm(side: str) -> str:
    j = ARMS[side]
    y = SHOULDER_Y if side == "l" else -SHOULDER_Y
    p = side
    return f"""
      <body name="{p}_shoulder_pan_link" pos="0 {y:g} 0" gravcomp="1">
        <inertial pos="0 0 -0.098" mass="25.8" diaginertia="0.87 0.87 0.27"/>
        {_hinge(j[0], "0 0 1")}
        <geom type="cylinder" pos="0 0 -0.08" size="0.095 0.13" rgba="{BLUE}"/>
        <body name="{p}_shoulder_lift_link" pos="{SHOULDER_LIFT_OFFSET:g} 0 0" gravcomp="1">
          <inertial pos="0.02 0 -0.03" mass="2.75" diaginertia="0.021 0.021 0.02"/>
          {_hinge(j[1], "0 1 0")}
          <geom type="cylinder" fromto="0 -0.07 0 0 0.07 0" size="0.07" rgba="{GREY}"/>
          <body name="{p}_upper_arm_roll_link" gravcomp="1">
            <inertial pos="0.214 0 0" mass="6.1" diaginertia="0.015 0.075 0.076"/>
            {_hinge(j[2], "1 0 0")}
            <geom type="capsule" fromto="0.08 0 0 0.32 0 0" size="0.055" rgba="{BLUE}"/>
            <body name="{p}_elbow_flex_link" pos="{UPPER_ARM:g} 0 0" gravcomp="1">
              <inertial pos="0.01 0 -0.012" mass="1.9" diaginertia="0.0035 0.0044 0.0036"/>
              {_hinge(j[3], "0 1 0")}
              <geom type="cylinder" fromto="0 -0.045 0 0 0.045 0" size="0.05" rgba="{GREY}"/>
              <body name="{p}_forearm_roll_link" gravcomp="1">
                <inertial pos="0.188 0 -0.009" mass="2.68" diaginertia="0.0036 0.015 0.0166"/>
                {_hinge(j[4], "1 0 0")}
                <geom type="capsule" fromto="0.06 0 0 0.27 0 0" size="0.045" rgba="{BLUE}"/>
                <body name="{p}_wrist_flex_link" pos="{FOREARM:g} 0 0" gravcomp="1">
                  <inertial pos="0 0 0" mass="0.614" diaginertia="0.00065 0.0002 0.00064"/>
                  {_hinge(j[5], "0 1 0")}
                  <geom type="cylinder" fromto="0 -0.03 0 0 0.03 0" size="0.03" rgba="{GREY}"/>
                  <body name="{p}_wrist_roll_link" gravcomp="1">
                    <inertial pos="0.066 0 0" mass="0.68" diaginertia="0.00035 0.00068 0.00087"/>
                    {_hinge(j[6], "1 0 0")}
                    <geom type="box" pos="0.06 0 0" size="0.04 0.04 0.025" rgba="{GREY}"/>
                    <site name="{p}_gripper_tool_frame" pos="{TOOL:g} 0 0" size="0.005"/>
                    {_finger(p, "l", 1)}
                    {_finger(p, "r", -1)}
                  </body>
                </body>
              </body>
            </body>
          </body>
        </body>
      </body>"""


def _finger(side: str, which: str, sign: int) -> str:
    """A finger that slides away from the gripper's centre line; its pad's inner face
    is at the joint's position, so the gap is the sum of the two joints."""
    half = GRIPPER_MAX / 2
    return f"""<body name="{side}_gripper_{which}_finger_link" gravcomp="1">
                      <inertial pos="0.145 0 0" mass="0.17" diaginertia="0.0001 0.0002 0.0002"/>
                      <joint name="{side}_gripper_{which}_finger_joint" type="slide"
                             axis="0 {sign} 0" range="0 {half:g}" armature="0.1"/>
                      <geom name="{side}_gripper_{which}_finger_pad" class="pad" type="box"
                            pos="0.145 {sign * 0.008:g} 0" size="0.055 0.008 0.015"/>
                    </body>"""


def robot_body() -> str:
    """The robot's bodies, rooted at base_footprint on the floor at the origin."""
    tx, ty, tz = TORSO_ORIGIN
    hx, hy, hz = HEAD_PAN_ORIGIN
    cx, cy, cz = CAMERA_OFFSET
    casters = "".join(
        f'<geom class="decor" type="cylinder" pos="{x:g} {y:g} 0.06" size="0.06 0.03"'
        f' rgba="{DARK}" euler="1.5708 0 0"/>'
        for x in (-0.25, 0.25)
        for y in (-0.25, 0.25)
    )
    return f"""
    <body name="base_footprint" childclass="robot">
      <joint name="base_x_joint" type="slide" axis="1 0 0" damping="0" armature="0"/>
      <joint name="base_y_joint" type="slide" axis="0 1 0" damping="0" armature="0"/>
      <joint name="base_yaw_joint" type="hinge" axis="0 0 1" damping="0" armature="0"/>
      <inertial pos="0 0 0.2" mass="116" diaginertia="5.6 5.6 8.0"/>
      <geom name="base" type="box" pos="0 0 {BASE_LINK_Z + 0.14:g}"
            size="{BASE_HALF:g} {BASE_HALF:g} 0.14" rgba="{GREY}"/>
      <geom class="decor" type="box" pos="-0.15 0 0.55" size="0.12 0.17 0.22" rgba="{WHITE}"/>
      {casters}
      <body name="torso_lift_link" pos="{tx:g} {ty:g} {tz:g}" gravcomp="1">
        <inertial pos="-0.1 0 -0.0885" mass="36.2" diaginertia="2.77 2.51 0.53"/>
        <joint name="{TORSO.name}" type="slide" axis="0 0 1"
               range="{TORSO.low:g} {TORSO.high:g}" armature="1"/>
        <geom type="box" pos="-0.13 0 0.1" size="0.1 0.15 0.25" rgba="{WHITE}"/>
        <body name="head_pan_link" pos="{hx:g} {hy:g} {hz:g}" gravcomp="1">
          <inertial pos="0.01 0 0.09" mass="6.34" diaginertia="0.032 0.047 0.058"/>
          {_hinge(HEAD[0], "0 0 1")}
          <geom class="decor" type="cylinder" pos="0 0 -0.03" size="0.05 0.05" rgba="{GREY}"/>
          <body name="{CAMERA_BODY}" pos="{HEAD_TILT_OFFSET:g} 0 0" gravcomp="1">
            <inertial pos="0 0 0.055" mass="4.48" diaginertia="0.024 0.055 0.067"/>
            {_hinge(HEAD[1], "0 1 0")}
            <geom type="box" pos="0.005 0 0.06" size="0.09 0.14 0.06" rgba="{BLUE}"/>
            <camera name="{CAMERA}" pos="{cx:g} {cy:g} {cz:g}" xyaxes="0 -1 0 0 0 1"
                    fovy="{CAMERA_FOVY:g}"/>
          </body>
        </body>
        {_arm("l")}
        {_arm("r")}
      </body>
    </body>"""


def actuators() -> str:
    """The base's velocity and hold actuators, then position servos: torso, head, arms,
    fingers."""
    lines = [
        f'<velocity name="{name}" joint="{name}_joint" kv="{kv:g}" forcerange="{-f:g} {f:g}"/>'
        for name, kv, _, f in BASE_SERVOS
    ]
    # The same commanded velocity, integrated: a spring to where the base should be, so
    # that a push (an arm against the table) does not make it drift.
    lines += [
        f'<intvelocity name="{name}_hold" joint="{name}_joint" kp="{kp:g}"'
        f' forcerange="{-f:g} {f:g}"/>'
        for name, _, kp, f in BASE_SERVOS
    ]
    for joint in (TORSO, *HEAD, *ARMS["l"], *ARMS["r"]):
        lines.append(
            f'<position name="{joint.name}" joint="{joint.name}" kp="{joint.kp:g}"'
            f' kv="{joint.kv:g}" ctrlrange="{joint.low:.6g} {joint.high:.6g}"'
            f' forcerange="{-joint.force:g} {joint.force:g}"/>'
        )
    for side in SIDES:
        for which in ("l", "r"):
            name = f"{side}_gripper_{which}_finger_joint"
            lines.append(
                f'<position name="{name}" joint="{name}" kp="{FINGER_KP:g}" kv="{FINGER_KV:g}"'
                f' ctrlrange="0 {GRIPPER_MAX / 2:g}"'
                f' forcerange="{-FINGER_FORCE:g} {FINGER_FORCE:g}"/>'
            )
    return "\n    ".join(lines)


def finger_pads(side: str) -> tuple[str, str]:
    """The names of the two finger pad geoms of gripper ``side``."""
    return f"{side}_gripper_l_finger_pad", f"{side}_gripper_r_finger_pad"
