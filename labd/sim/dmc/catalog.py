"""The pack's tasks as data: what the lab must know of each without building it.

A task's topics, parameters, export layout and docs are needed before any episode
exists (``TaskSpec.topics()`` reads the task class; the API lists every task), and
building a dm_control environment to learn them would make ``import labd.sim.dmc``
slow. So each task is listed here with what ``dm_control.suite.load`` would tell:
its episode length, control timestep, actuators (the action spec's order), observation
keys and shapes, and the camera the suite renders by default (camera 0). The tests
build every listed task and hold each of these to the real environment.

Each task also has its **return threshold**, the episode return (out of the suite's
1000) at which it counts as solved, with the reason for that number; docs/tasks.md
tables them with the returns of zero and of random actions on the dev seeds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

Shape = tuple[int, ...]

# Why a threshold is what it is (docs/tasks.md explains each kind):
HOLD = "hold"  # the reward can be earned from (nearly) the first step: 90 % of 1000
REACH_FIRST = "reach first"  # the rewarded state takes part of the episode to reach
SPEED = "speed"  # the reward saturates at a speed only strong controllers reach


@dataclass(frozen=True)
class Listing:
    """One task of ``dm_control.suite`` as the pack serves it."""

    domain: str
    task: str
    time_limit: float  # s: the suite's episode (its step limit times the control timestep)
    control_timestep: float  # s: one lab tick, one environment step
    actuators: tuple[str, ...]  # the action spec's order
    bounds: tuple[tuple[float, float], ...]  # each actuator's (minimum, maximum)
    observations: tuple[tuple[str, Shape], ...]  # the observation dict's keys, in order
    camera: str  # the model's camera 0, which the suite renders by default
    threshold: float  # the return at which an episode counts as solved
    basis: str  # why the threshold is what it is: HOLD, REACH_FIRST or SPEED
    goal: str  # the task in words (an export's instruction)

    @property
    def name(self) -> str:
        return f"dmc-{self.domain}-{self.task}"

    @property
    def steps(self) -> int:
        """The suite's episode length in steps."""
        return round(self.time_limit / self.control_timestep)

    @property
    def action_size(self) -> int:
        return len(self.actuators)

    def size(self, key: str) -> int:
        """How many numbers the observation ``key`` holds, flattened."""
        return math.prod(dict(self.observations)[key])


def _listings(
    domain: str,
    *,
    time_limit: float,
    control_timestep: float,
    actuators: tuple[str, ...],
    observations: tuple[tuple[str, Shape], ...],
    camera: str,
    tasks: tuple[tuple[str, float, str, str], ...],
    own: dict[str, tuple[tuple[str, Shape], ...]] | None = None,
    bounds: tuple[tuple[float, float], ...] | None = None,
) -> tuple[Listing, ...]:
    """A domain's tasks: (task, threshold, basis, goal) each; ``own`` observations for
    the tasks whose keys are not the domain's common ones; ``bounds`` of the actuators
    where they are not all [-1, 1]."""
    out = []
    for task, threshold, basis, goal in tasks:
        keys = (own or {}).get(task, observations)
        out.append(
            Listing(
                domain,
                task,
                time_limit,
                control_timestep,
                actuators,
                bounds or ((-1.0, 1.0),) * len(actuators),
                keys,
                camera,
                threshold,
                basis,
                goal,
            )
        )
    return tuple(out)


_WALKER = ("right_hip", "right_knee", "right_ankle", "left_hip", "left_knee", "left_ankle")
_CHEETAH = ("bthigh", "bshin", "bfoot", "fthigh", "fshin", "ffoot")
_FISH = ("tail", "tail_twist", "fins_flap", "finleft_pitch", "finright_pitch")
_QUADRUPED = tuple(
    f"{joint}_{leg}"
    for leg in ("front_left", "front_right", "back_right", "back_left")
    for joint in ("yaw", "lift", "extend")
)
_QUADRUPED_BOUNDS = ((-1.0, 1.0), (-1.0, 1.1), (-0.8, 0.8)) * 4
_LEG = ("hip_x", "hip_z", "hip_y", "knee", "ankle_x", "ankle_y")
_ARM = ("shoulder1", "shoulder2", "elbow")
_HUMANOID = (
    "abdomen_y",
    "abdomen_z",
    "abdomen_x",
    *(f"{side}_{joint}" for side in ("right", "left") for joint in _LEG),
    *(f"{side}_{joint}" for side in ("right", "left") for joint in _ARM),
)

_FINGER_TURN = (
    ("position", (4,)),
    ("velocity", (3,)),
    ("touch", (2,)),
    ("target_position", (2,)),
    ("dist_to_target", ()),
)
_FISH_SWIM = (("joint_angles", (7,)), ("upright", ()), ("target", (3,)), ("velocity", (13,)))

CATALOG: tuple[Listing, ...] = (
    *_listings(
        "cartpole",
        time_limit=10.0,
        control_timestep=0.01,
        actuators=("slide",),
        observations=(("position", (3,)), ("velocity", (2,))),
        camera="fixed",
        tasks=(
            ("balance", 900.0, HOLD, "keep the pole upright with the cart near the centre"),
            ("balance_sparse", 900.0, HOLD, "keep the pole upright and the cart on the track"),
            ("swingup", 800.0, REACH_FIRST, "swing the pole up and balance it"),
            ("swingup_sparse", 700.0, REACH_FIRST, "swing the pole up and balance it"),
        ),
    ),
    *_listings(
        "reacher",
        time_limit=20.0,
        control_timestep=0.02,
        actuators=("shoulder", "wrist"),
        observations=(("position", (2,)), ("to_target", (2,)), ("velocity", (2,))),
        camera="fixed",
        tasks=(
            ("easy", 900.0, HOLD, "put the fingertip on the large target"),
            ("hard", 900.0, HOLD, "put the fingertip on the small target"),
        ),
    ),
    *_listings(
        "walker",
        time_limit=25.0,
        control_timestep=0.025,
        actuators=_WALKER,
        observations=(("orientations", (14,)), ("height", ()), ("velocity", (9,))),
        camera="side",
        tasks=(
            ("stand", 900.0, HOLD, "stand up and stay upright"),
            ("walk", 900.0, HOLD, "walk forward at 1 m/s"),
            ("run", 700.0, SPEED, "run forward at 8 m/s"),
        ),
    ),
    *_listings(
        "cheetah",
        time_limit=10.0,
        control_timestep=0.01,
        actuators=_CHEETAH,
        observations=(("position", (8,)), ("velocity", (9,))),
        camera="side",
        tasks=(("run", 700.0, SPEED, "run forward at 10 m/s"),),
    ),
    *_listings(
        "finger",
        time_limit=20.0,
        control_timestep=0.02,
        actuators=("proximal", "distal"),
        observations=(("position", (4,)), ("velocity", (3,)), ("touch", (2,))),
        camera="cam0",
        tasks=(
            ("spin", 800.0, REACH_FIRST, "spin the hinged body fast"),
            ("turn_easy", 900.0, HOLD, "turn the body's tip into the large target"),
            ("turn_hard", 900.0, HOLD, "turn the body's tip into the small target"),
        ),
        own={task: _FINGER_TURN for task in ("turn_easy", "turn_hard")},
    ),
    *_listings(
        "ball_in_cup",
        time_limit=20.0,
        control_timestep=0.02,
        actuators=("x", "z"),
        observations=(("position", (4,)), ("velocity", (4,))),
        camera="cam0",
        tasks=(("catch", 900.0, HOLD, "swing the ball into the cup and keep it there"),),
    ),
    *_listings(
        "pendulum",
        time_limit=20.0,
        control_timestep=0.02,
        actuators=("torque",),
        observations=(("orientation", (2,)), ("velocity", (1,))),
        camera="fixed",
        tasks=(("swingup", 750.0, REACH_FIRST, "swing the pendulum up and hold it"),),
    ),
    *_listings(
        "acrobot",
        time_limit=10.0,
        control_timestep=0.01,
        actuators=("elbow",),
        observations=(("orientations", (4,)), ("velocity", (2,))),
        camera="fixed",
        tasks=(("swingup", 500.0, REACH_FIRST, "swing the tip up and hold it there"),),
    ),
    *_listings(
        "hopper",
        time_limit=20.0,
        control_timestep=0.02,
        actuators=("waist", "hip", "knee", "ankle"),
        observations=(("position", (6,)), ("velocity", (7,)), ("touch", (2,))),
        camera="cam0",
        tasks=(
            ("stand", 800.0, REACH_FIRST, "get up and stand upright"),
            ("hop", 300.0, SPEED, "hop forward at 2 m/s"),
        ),
    ),
    *_listings(
        "point_mass",
        time_limit=20.0,
        control_timestep=0.02,
        actuators=("t1", "t2"),
        observations=(("position", (2,)), ("velocity", (2,))),
        camera="fixed",
        tasks=(("easy", 900.0, HOLD, "bring the mass to the target and keep it there"),),
    ),
    *_listings(
        "fish",
        time_limit=40.0,
        control_timestep=0.04,
        actuators=_FISH,
        observations=(("joint_angles", (7,)), ("upright", ()), ("velocity", (13,))),
        camera="tracking_top",
        tasks=(
            ("upright", 900.0, HOLD, "turn upright and stay so"),
            ("swim", 600.0, SPEED, "swim to the target and stay there"),
        ),
        own={"swim": _FISH_SWIM},
    ),
    *_listings(
        "swimmer",
        time_limit=30.0,
        control_timestep=0.03,
        actuators=tuple(f"motor_{i}" for i in range(5)),
        observations=(("joints", (5,)), ("to_target", (2,)), ("body_velocities", (18,))),
        camera="tracking1",
        tasks=(("swimmer6", 700.0, SPEED, "swim the nose to the target and keep it there"),),
    ),
    *_listings(
        "quadruped",
        time_limit=20.0,
        control_timestep=0.02,
        actuators=_QUADRUPED,
        bounds=_QUADRUPED_BOUNDS,
        observations=(
            ("egocentric_state", (44,)),
            ("torso_velocity", (3,)),
            ("torso_upright", ()),
            ("imu", (6,)),
            ("force_torque", (24,)),
        ),
        camera="global",
        tasks=(
            ("walk", 800.0, REACH_FIRST, "walk forward at 0.5 m/s"),
            ("run", 600.0, SPEED, "run forward at 5 m/s"),
        ),
    ),
    *_listings(
        "humanoid",
        time_limit=25.0,
        control_timestep=0.025,
        actuators=_HUMANOID,
        observations=(
            ("joint_angles", (21,)),
            ("head_height", ()),
            ("extremities", (12,)),
            ("torso_vertical", (3,)),
            ("com_velocity", (3,)),
            ("velocity", (27,)),
        ),
        camera="back",
        tasks=(
            ("stand", 800.0, REACH_FIRST, "get up and stand upright"),
            ("walk", 700.0, SPEED, "get up and walk forward at 1 m/s"),
        ),
    ),
)
