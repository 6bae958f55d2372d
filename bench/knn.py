"""The kNN example's success rate against how many demonstrations it learnt from.

    .venv/bin/python bench/knn.py [--seeds 20] [--demos 5 10 20] [--time-limit 180]

Scripted demonstrations (``labd.scripted``: a driver that knows the maze drives a live
robot, each drive recorded as the lab records a person's) are converted as a trial's
``LAB_DATA_DIR`` is (``labd.exports.write_dataset``); the example's policy
(``controllers/examples/knn-maze``) learns from the first N of them and drives
icreate-maze in lockstep, in this process, on seeds 0 .. seeds-1 (the demonstrations are
of other seeds: other mazes). A random policy (uniform commands, seeded) drives the same
seeds as the baseline. Prints the success rate, the mean reward (metres of progress along
the corridors, +10 at the goal) and the time each took.
"""

from __future__ import annotations

import argparse
import importlib.util
import logging
import random
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from labd.graph.graph import Graph, Side
from labd.graph.types import TypeRegistry
from labd.live import Driving
from labd.scripted import demonstrate
from labd.sim.robot import Robot
from labd.station import Station
from labd.exports import write_dataset

ROOT = Path(__file__).resolve().parent.parent
TASK = "icreate-maze"


def load_knn() -> Any:
    path = ROOT / "controllers" / "examples" / "knn-maze" / "controller.py"
    spec = importlib.util.spec_from_file_location("knn_controller", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def demonstrations(count: int, folder: Path, seed: int = 1000) -> list[tuple[dict[str, Any], Path]]:
    """``count`` successful scripted drives of seeds after ``seed``, as pinned records."""
    station = Station(
        TypeRegistry.default(), "icreate-1", TASK, {}, seed, live=True, protected_prefixes=()
    )
    driving = Driving(station, work=folder)
    records = []
    try:
        while len(records) < count:
            demo = demonstrate(station, driving, user="script")
            if demo is None or not demo.achieved:
                continue
            known = {"trial": len(records) + 1, "kind": "demonstration", "task": TASK,
                     "seed": demo.seed, "outcome": "success", "data_digest": demo.data_digest}
            records.append((known, demo.folder / "trial.mcap"))
    finally:
        driving.close()
        station.close()
    return records


Act = Callable[[dict[str, Any], dict[str, Any], dict[str, Any]], tuple[float, float]]


def drive(act: Act, seed: int, time_limit: float) -> dict[str, Any]:
    """One lockstep episode in this process; the task's metrics."""
    graph = Graph(TypeRegistry.default(), name="bench-knn")
    robot = Robot(graph, TASK, {"time_limit": time_limit}, seed)
    client = graph.create_node("/policy", side=Side.CLIENT)
    latest: dict[str, Any] = {}
    for topic in ("/odom", "/bumper", "/goal"):
        client.subscribe(topic, None, lambda m, t=topic: latest.__setitem__(t, m.data))
    cmd = client.advertise("/cmd_vel", "geometry_msgs/msg/Twist")
    try:
        robot.publish()
        while robot.sim.running:
            v, w = act(latest["/odom"], latest["/goal"], latest["/bumper"])
            cmd.publish({"linear": {"x": v}, "angular": {"z": w}})
            robot.step()
        return dict(robot.sim.metrics())
    finally:
        robot.close()


def evaluate(name: str, act_for: Callable[[int], Act], seeds: int, limit: float) -> dict[str, Any]:
    started = time.perf_counter()
    runs = [drive(act_for(seed), seed, limit) for seed in range(seeds)]
    wins = sum(bool(r["success"]) for r in runs)
    reward = sum(float(r["reward"]) for r in runs) / len(runs)
    out = {"policy": name, "successes": wins, "seeds": seeds, "mean_reward": reward,
           "seconds": time.perf_counter() - started}
    print(f"{name:<28} {wins:>3}/{seeds} = {wins / seeds:5.0%}   mean reward {reward:6.2f}"
          f"   ({out['seconds']:.0f} s)", flush=True)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=20)
    parser.add_argument("--demos", type=int, nargs="+", default=[5, 10, 20])
    parser.add_argument("--time-limit", type=float, default=180.0)
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING)
    knn = load_knn()
    with tempfile.TemporaryDirectory(prefix="labd-bench-knn-") as tmp:
        folder = Path(tmp)
        started = time.perf_counter()
        records = demonstrations(max(args.demos), folder / "live")
        print(f"{len(records)} scripted demonstrations in {time.perf_counter() - started:.0f} s")

        def rng_policy(seed: int) -> Act:
            rng = random.Random(seed)
            return lambda *_: (rng.uniform(-0.5, 0.5), rng.uniform(-4.2, 4.2))

        evaluate("random", rng_policy, args.seeds, args.time_limit)
        for n in args.demos:
            data = folder / f"data-{n}"
            write_dataset(records[:n], data)
            policy = knn.Policy(data / TASK / "arrays.npz")

            def act(odom: Any, goal: Any, bumper: Any, policy: Any = policy) -> tuple[float, float]:
                return policy.act(knn.features(knn.observe(odom, goal, bumper)))

            evaluate(f"kNN, {n} demonstrations", lambda _seed, act=act: act, args.seeds, args.time_limit)


if __name__ == "__main__":
    main()
