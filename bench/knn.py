"""The kNN example's success rate against how many demonstrations it learnt from.

    .venv/bin/python bench/knn.py [--seeds 20] [--demos 5 10 20] [--time-limit 180]

Scripted demonstrations (``labd.scripted``: a driver that knows the maze drives a live
robot, each drive recorded as the lab records a person's), one of each maze of seeds
0 .. seeds-1, are converted as a trial's ``LAB_DATA_DIR`` is
(``labd.exports.write_dataset``). The example's policy (``controllers/examples/knn-maze``)
learns from the first N of them (the mazes of seeds 0 .. N-1) and drives icreate-maze in
lockstep, in this process, on every seed 0 .. seeds-1: so it is tried on N mazes it was
shown and seeds-N it was not. Baselines on the same seeds: a random policy (uniform
commands, seeded), and the kNN learning from as many demonstrations of other mazes
(seeds 1000 and up). Prints the success rate, the mean reward (metres of progress along
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

from labd.exports import write_dataset
from labd.graph.graph import Graph, Side
from labd.graph.types import TypeRegistry
from labd.live import Driving
from labd.scripted import demonstrate
from labd.sim.robot import Robot
from labd.station import Station

ROOT = Path(__file__).resolve().parent.parent
TASK = "icreate-maze"


def load_knn() -> Any:
    path = ROOT / "controllers" / "examples" / "knn-maze" / "controller.py"
    spec = importlib.util.spec_from_file_location("knn_controller", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def demonstrations(seeds: list[int], folder: Path) -> list[tuple[dict[str, Any], Path]]:
    """A successful scripted drive of each of the mazes of ``seeds``, as pinned records."""
    station = Station(
        TypeRegistry.default(), "icreate-1", TASK, {}, 0, live=True, protected_prefixes=()
    )
    driving = Driving(station, work=folder)
    records = []
    try:
        for seed in seeds:
            demo = demonstrate(station, driving, user="script", seed=seed)
            if demo is None or not demo.achieved:
                raise RuntimeError(f"the scripted driver failed on seed {seed}")
            known = {
                "trial": len(records) + 1,
                "kind": "demonstration",
                "task": TASK,
                "seed": demo.seed,
                "outcome": "success",
                "data_digest": demo.data_digest,
            }
            records.append((known, demo.folder / "trial.mcap"))
    finally:
        driving.close()
        station.close()
    return records


Act = Callable[[dict[str, Any], dict[str, Any]], tuple[float, float]]


def drive(act: Act, seed: int, time_limit: float) -> dict[str, Any]:
    """One lockstep episode in this process; the task's metrics."""
    graph = Graph(TypeRegistry.default(), name="bench-knn")
    robot = Robot(graph, TASK, {"time_limit": time_limit}, seed)
    client = graph.create_node("/policy", side=Side.CLIENT)
    latest: dict[str, Any] = {}
    for topic in ("/odom", "/goal"):
        client.subscribe(topic, None, lambda m, t=topic: latest.__setitem__(t, m.data))
    cmd = client.advertise("/cmd_vel", "geometry_msgs/msg/Twist")
    try:
        robot.publish()
        while robot.sim.running:
            v, w = act(latest["/odom"], latest["/goal"])
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
    out = {
        "policy": name,
        "successes": wins,
        "seeds": seeds,
        "mean_reward": reward,
        "seconds": time.perf_counter() - started,
    }
    print(
        f"{name:<28} {wins:>3}/{seeds} = {wins / seeds:5.0%}   mean reward {reward:6.2f}"
        f"   ({out['seconds']:.0f} s)",
        flush=True,
    )
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
        most = max(args.demos)
        shown = demonstrations(list(range(most)), folder / "live")
        others = demonstrations(list(range(1000, 1000 + most)), folder / "live")
        print(f"{2 * most} scripted demonstrations in {time.perf_counter() - started:.0f} s")

        def rng_policy(seed: int) -> Act:
            rng = random.Random(seed)
            return lambda *_: (rng.uniform(-0.5, 0.5), rng.uniform(-4.2, 4.2))

        evaluate("random", rng_policy, args.seeds, args.time_limit)
        for n in args.demos:
            for name, records in (
                (f"kNN, {n} demonstrations", shown),
                ("  of other mazes", others),
            ):
                data = folder / f"data-{name}-{n}"
                write_dataset(records[:n], data)
                policy = knn.Policy(data / TASK / "arrays.npz")

                def act(odom: Any, goal: Any, policy: Any = policy) -> tuple[float, float]:
                    return policy.act(knn.features(knn.observe(odom, goal)))

                evaluate(name, lambda _seed, act=act: act, args.seeds, args.time_limit)


if __name__ == "__main__":
    main()
