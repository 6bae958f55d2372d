"""A tiny task for testing the robot node without a real robot: a puck on a plane.

The puck is driven by a velocity command on /cmd_vel and reports its position on
/pose. It succeeds when it gets within 0.1 m of (1, 0), and diverges on purpose when
/explode asks for it, so the failure path can be tested.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from dm_control import mujoco
from dm_control.rl import control
from dm_env import specs

from labd.sim.base import (
    CommandTopic,
    LabTask,
    ObservationTopic,
    Outcome,
    finite,
)
from labd.sim.params import Param, Params
from labd.sim.registry import TaskSpec
from repository.trial import EpisodeStatus

XML = """
<mujoco model="puck">
  <option timestep="0.01"/>
  <worldbody>
    <geom name="floor" type="plane" size="5 5 0.1"/>
    <camera name="top" pos="0 0 3"/>
    <body name="puck" pos="0 0 0.05">
      <joint name="x" type="slide" axis="1 0 0" damping="1"/>
      <joint name="y" type="slide" axis="0 1 0" damping="1"/>
      <geom name="puck" type="cylinder" size="0.05 0.05" mass="1" contype="0" conaffinity="0"/>
    </body>
  </worldbody>
  <actuator>
    <velocity name="vx" joint="x" kv="50" ctrlrange="-1 1" ctrllimited="true"/>
    <velocity name="vy" joint="y" kv="50" ctrlrange="-1 1" ctrllimited="true"/>
  </actuator>
</mujoco>
"""


class PointMass(LabTask):
    name = "pointmass"
    version = "1"
    params = Params(
        [
            Param("time_limit", 2.0, "seconds", minimum=0.1, maximum=100.0),
            Param("goal_x", 1.0, "where the goal is, metres", minimum=-4.0, maximum=4.0),
        ]
    )
    commands = (
        CommandTopic("/cmd_vel", "geometry_msgs/msg/Twist", "velocity, m/s"),
        CommandTopic("/explode", "std_msgs/msg/Bool", "make the physics diverge"),
    )
    observations = (
        ObservationTopic("/pose", "geometry_msgs/msg/PointStamped", "where the puck is"),
        ObservationTopic("/slow", "std_msgs/msg/UInt32", "the tick, every 5 ticks", period=5),
        ObservationTopic(
            "/camera/image/compressed",
            "sensor_msgs/msg/CompressedImage",
            "a camera (fake)",
            on_demand=True,
        ),
    )

    def __init__(self, params: dict[str, Any], random: np.random.RandomState) -> None:
        super().__init__(params, random)
        self.velocity = np.zeros(2)
        self.explode = False
        self.renders = 0

    def command(self, topic: str, data: dict[str, Any]) -> None:
        if topic == "/explode":
            self.explode = bool(data["data"])
            return
        vx = finite(data["linear"]["x"], "linear", "x")
        vy = finite(data["linear"]["y"], "linear", "y")
        self.velocity = np.array([self.clip(topic, vx, -1, 1), self.clip(topic, vy, -1, 1)])

    def action(self, physics: Any) -> np.ndarray:
        return self.velocity.copy()

    def before_step(self, action: np.ndarray, physics: Any) -> None:
        physics.set_control(action)
        if self.explode:
            physics.data.qacc_warmstart[:] = np.nan
            physics.data.qpos[0] = np.nan

    def get_observation(self, physics: Any) -> dict[str, np.ndarray]:
        return {"position": physics.data.qpos[:2].copy()}

    def get_reward(self, physics: Any) -> float:
        return float(-abs(physics.data.qpos[0] - self.values["goal_x"]))

    def get_termination(self, physics: Any) -> float | None:
        return 0.0 if self.outcome(physics) is not None else None

    def action_spec(self, physics: Any) -> specs.BoundedArray:
        return specs.BoundedArray((2,), float, -1.0, 1.0)

    def observe(self, physics: Any, topic: str, stamp: dict[str, int]) -> dict[str, Any] | None:
        if topic == "/pose":
            x, y = physics.data.qpos[:2]
            return {
                "header": {"stamp": stamp, "frame_id": "world"},
                "point": {"x": float(x), "y": float(y), "z": 0.0},
            }
        if topic == "/slow":
            return {"data": round(physics.data.time / 0.1)}
        self.renders += 1
        return {"header": {"stamp": stamp, "frame_id": "top"}, "format": "jpeg", "data": b"\xff"}

    def outcome(self, physics: Any) -> Outcome | None:
        if abs(physics.data.qpos[0] - self.values["goal_x"]) < 0.1:
            return Outcome(EpisodeStatus.SUCCEEDED, "reached the goal")
        if abs(physics.data.qpos[1]) > 2:
            return Outcome(EpisodeStatus.FAILED, "left the plane")
        return None

    def metrics(self, physics: Any) -> dict[str, bool | int | float]:
        return {
            "success": self.outcome(physics) is not None,
            "reward": self.get_reward(physics),
            "clipped_commands": sum(self.clipped.values()),
        }


def make(
    values: dict[str, Any],
    seed: int,
    *,
    time_limit: float | None = None,
    kind: type[PointMass] = PointMass,
) -> control.Environment:
    physics = mujoco.Physics.from_xml_string(XML)
    task = kind(values, np.random.RandomState(seed))
    task.model_xml = XML
    limit = values["time_limit"] if time_limit is None else time_limit
    return control.Environment(physics, task, time_limit=limit, control_timestep=0.1)


TASK = TaskSpec(
    name="pointmass", version="1", doc="a puck for tests", params=PointMass.params, build=make
)
