"""A puck on a table, pushed by a velocity command to a goal: a task for the lab.

Everything the lab needs of the task is here: its model, its dm_control Task with a ROS
face (LabTask), its parameters, its topics, its export layout, its episode suites. The
lab finds it through the entry point in pyproject.toml.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from dm_control import mujoco
from dm_control.rl import control
from dm_env import specs

from labd.sim.base import CommandTopic, LabTask, ObservationTopic, Outcome, finite
from labd.sim.features import field
from labd.sim.params import Param, Params
from labd.sim.registry import TaskSpec
from repository.evaluation import Suite
from repository.export import Layout
from repository.trial import EpisodeStatus

XML = """
<mujoco model="puck">
  <option timestep="0.01"/>
  <worldbody>
    <light pos="0 0 3"/>
    <geom name="table" type="plane" size="2 2 0.1" rgba=".8 .8 .8 1"/>
    <camera name="top" pos="0 0 4"/>
    <body name="puck" pos="0 0 0.05">
      <joint name="x" type="slide" axis="1 0 0" damping="1"/>
      <joint name="y" type="slide" axis="0 1 0" damping="1"/>
      <geom name="puck" type="cylinder" size="0.05 0.05" mass="1" rgba=".9 .2 .1 1"/>
    </body>
  </worldbody>
  <actuator>
    <velocity name="vx" joint="x" kv="50" ctrlrange="-1 1" ctrllimited="true"/>
    <velocity name="vy" joint="y" kv="50" ctrlrange="-1 1" ctrllimited="true"/>
  </actuator>
</mujoco>
"""


class Puck(LabTask):
    name = "puck"
    version = "1"
    params = Params(
        [
            Param("time_limit", 5.0, "seconds of simulation time", minimum=0.5, maximum=60.0),
            Param("goal_x", 1.0, "where the goal is on x, metres", minimum=-1.5, maximum=1.5),
        ]
    )
    commands = (CommandTopic("/cmd_vel", "geometry_msgs/msg/Twist", "linear.x, linear.y: m/s"),)
    observations = (
        ObservationTopic("/pose", "geometry_msgs/msg/PointStamped", "where the puck is"),
        ObservationTopic("/goal", "geometry_msgs/msg/PointStamped", "the goal", period=0),
    )

    def __init__(self, params: dict[str, Any], random: np.random.RandomState) -> None:
        super().__init__(params, random)
        self.velocity = np.zeros(2)
        self.start = random.uniform(-0.5, 0.5, size=2)  # the seed places the puck

    def initialize_episode(self, physics: Any) -> None:
        physics.data.qpos[:2] = self.start

    def command(self, topic: str, data: dict[str, Any]) -> None:
        vx = finite(data["linear"]["x"], "linear", "x")
        vy = finite(data["linear"]["y"], "linear", "y")
        self.velocity = np.array([self.clip(topic, vx, -1, 1), self.clip(topic, vy, -1, 1)])

    def action(self, physics: Any) -> np.ndarray:
        return self.velocity.copy()

    def before_step(self, action: np.ndarray, physics: Any) -> None:
        physics.set_control(action)

    def get_observation(self, physics: Any) -> dict[str, np.ndarray]:
        return {"position": physics.data.qpos[:2].copy()}

    def get_reward(self, physics: Any) -> float:
        return float(-self._distance(physics))

    def get_termination(self, physics: Any) -> float | None:
        return 0.0 if self.outcome(physics) is not None else None

    def action_spec(self, physics: Any) -> specs.BoundedArray:
        return specs.BoundedArray((2,), float, -1.0, 1.0)

    def observe(self, physics: Any, topic: str, stamp: dict[str, int]) -> dict[str, Any] | None:
        x, y = (physics.data.qpos[:2]) if topic == "/pose" else (self.values["goal_x"], 0.0)
        return {
            "header": {"stamp": stamp, "frame_id": "world"},
            "point": {"x": float(x), "y": float(y), "z": 0.0},
        }

    def outcome(self, physics: Any) -> Outcome | None:
        if self._distance(physics) < 0.05:
            return Outcome(EpisodeStatus.SUCCEEDED, "the puck reached the goal")
        return None

    def metrics(self, physics: Any) -> dict[str, bool | int | float]:
        return {
            "success": self.outcome(physics) is not None,
            "reward": self.get_reward(physics),
            "distance": self._distance(physics),
        }

    def _distance(self, physics: Any) -> float:
        x, y = physics.data.qpos[:2]
        return float(np.hypot(x - self.values["goal_x"], y))


def make(
    values: dict[str, Any], seed: int, *, time_limit: float | None = None
) -> control.Environment:
    """One episode: the puck placed by ``seed``."""
    physics = mujoco.Physics.from_xml_string(XML)
    task = Puck(values, np.random.RandomState(seed))
    task.model_xml = XML
    limit = values["time_limit"] if time_limit is None else time_limit
    return control.Environment(physics, task, time_limit=limit, control_timestep=0.1)


LAYOUT = Layout(
    task="puck",
    version="1",
    observation=(
        field("/pose", lambda m: m.point.x, "puck.x", "m", "the puck's position"),
        field("/pose", lambda m: m.point.y, "puck.y", "m", "the puck's position"),
        field("/goal", lambda m: m.point.x, "goal.x", "m", "the goal's position"),
    ),
    action=(
        field("/cmd_vel", lambda m: m.linear.x, "cmd_vel.x", "m/s", "velocity along x"),
        field("/cmd_vel", lambda m: m.linear.y, "cmd_vel.y", "m/s", "velocity along y"),
    ),
    cameras=(),
    instruction=lambda _messages: "push the puck to the goal",
)

TASK = TaskSpec(
    name=Puck.name,
    version=Puck.version,
    doc="A puck on a table, pushed by a velocity command to a goal on the x axis.",
    params=Puck.params,
    build=make,
    task_class=Puck,
    layout=LAYOUT,
    camera="top",
    suites=(Suite("dev", 1, seeds=tuple(range(5)), doc="5 starts, seeds 0 to 4"),),
)
