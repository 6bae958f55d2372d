"""A k-nearest-neighbours policy for icreate-maze, learnt from demonstrations.

The rosjs paper's own example of the lab's loop: people drive the robot, the lab keeps
their drives, and a controller that learns from them drives the robot in turn. The
demonstrations are in ``LAB_DATA_DIR`` (the lab pins them when the trial is submitted;
docs/trials.md, "Data to learn from"): ``lerobot/icreate-maze/arrays.npz`` holds every
demonstrated control tick, the observation entries of the task's export layout
(docs/tasks.md) and the command the driver gave then.

The policy reads what the robot senses: its odometry (where it is and which way it
faces, from where it started) and ``/goal`` (where the goal is, in the same frame). Each
tick it finds the ``K`` demonstrated ticks nearest to its own (the goal's offset from the
robot, its heading, and the goal's place, each scaled by its spread in the data) and
commands the distance-weighted mean of their ``/cmd_vel``. The goal's place tells one
maze from another, so it drives the mazes it was shown, along the demonstrated routes,
and steers back onto them when it strays; in a maze no one demonstrated it has nothing
to go on but heading for the goal, and a wall stops it. No map, no planner: it is as
good as its data. It uses NumPy and the lab's client library only, and nothing random,
so the same data and seed give the same run.
"""

from __future__ import annotations

import logging
import math
import os
import sys
from pathlib import Path

import numpy as np

from controllers.client import EpisodeOver, Lab, Message

K = 5
FEATURES = ("odom.x", "odom.y", "odom.yaw", "goal.x", "goal.y")
DATASET = Path("lerobot") / "icreate-maze" / "arrays.npz"
log = logging.getLogger("knn")


def features(values: dict[str, float]) -> np.ndarray:
    """The policy's view of one tick: the goal's offset from the robot (m), its heading as
    a unit vector (so that -pi and pi are neighbours), and the goal's place (m)."""
    yaw = values["odom.yaw"]
    return np.array(
        [
            values["goal.x"] - values["odom.x"],
            values["goal.y"] - values["odom.y"],
            math.cos(yaw),
            math.sin(yaw),
            values["goal.x"],
            values["goal.y"],
        ]
    )


class Policy:
    """The demonstrated ticks, as features and commands."""

    def __init__(self, data: Path) -> None:
        arrays = np.load(data)
        names = [str(n) for n in arrays["observation_names"]]
        columns = {name: arrays["observation"][:, names.index(name)] for name in FEATURES}
        rows = [
            dict(zip(FEATURES, values, strict=True))
            for values in zip(*columns.values(), strict=True)
        ]
        self.inputs = np.array([features(row) for row in rows])
        actions = [str(n) for n in arrays["action_names"]]
        picked = [actions.index("cmd_vel.linear.x"), actions.index("cmd_vel.angular.z")]
        self.outputs = arrays["action"][:, picked].astype(np.float64)
        self.scale = self.inputs.std(axis=0) + 1e-6
        episodes = len(set(arrays["episode"].tolist()))
        log.info("learnt from %d ticks of %d demonstrations", len(self.inputs), episodes)

    def act(self, now: np.ndarray) -> tuple[float, float]:
        distances = np.linalg.norm((self.inputs - now) / self.scale, axis=1)
        nearest = np.argsort(distances, kind="stable")[:K]
        weights = 1.0 / (distances[nearest] + 1e-3)
        v, w = (self.outputs[nearest] * weights[:, None]).sum(axis=0) / weights.sum()
        return float(v), float(w)


def observe(odom: Message, goal: Message) -> dict[str, float]:
    """The layout's entries the policy uses, computed as the lab's export computes them."""
    pose = odom["pose"]["pose"]
    q = pose["orientation"]
    return {
        "odom.x": pose["position"]["x"],
        "odom.y": pose["position"]["y"],
        "odom.yaw": math.atan2(
            2 * (q["w"] * q["z"] + q["x"] * q["y"]), 1 - 2 * (q["y"] ** 2 + q["z"] ** 2)
        ),
        "goal.x": goal["point"]["x"],
        "goal.y": goal["point"]["y"],
    }


def main() -> int:
    logging.basicConfig(level=logging.INFO, format="%(name)s: %(message)s")
    folder = os.environ.get("LAB_DATA_DIR")
    if not folder or not (Path(folder) / DATASET).is_file():
        log.error("no demonstrations: lab.toml's [data] must pin some (LAB_DATA_DIR/%s)", DATASET)
        return 2
    policy = Policy(Path(folder) / DATASET)
    with Lab.connect() as lab:
        odom = lab.subscribe("/odom", "nav_msgs/msg/Odometry")
        goal = lab.subscribe("/goal", "geometry_msgs/msg/PointStamped").get()
        odom.get()
        try:
            while True:
                now = features(observe(odom.get(), goal))
                v, w = policy.act(now)
                lab.publish(
                    "/cmd_vel", "geometry_msgs/msg/Twist", {"linear": {"x": v}, "angular": {"z": w}}
                )
                lab.step()
        except EpisodeOver as end:
            log.info("%s: %s", end.status, end.reason)
    return 0


if __name__ == "__main__":
    sys.exit(main())
