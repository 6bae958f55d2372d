"""What a benchmark run costs: a `dmc-classic` run through `labd serve`, against the physics.

A controller that steps every tick and sends nothing (its actions stay zero; every task
of the benchmark plays its whole episode, 1,000 ticks) is run on every task of a
benchmark (``dmc-classic`` by default, 6 tasks on their dev suites: 120 episodes)
through a real ``labd serve`` with bubblewrap, submitted and followed through the API
as ``labd evaluate --benchmark`` does, with the lab's defaults (every record replayed
to verify it). Each way prints the run's wall time from submitting to the last
replay's verdict, the machine's CPU seconds per verified episode, and the ratio of
that to the same episodes' ticks stepped in this process with no controller, no
sandbox, no recording (the physics alone):

- **local**: ``labd serve --workers 2`` (this machine's two cores);
- **cluster**: ``labd serve --workers 0 --ray-address ADDRESS`` on a loopback Ray
  cluster of two one-slot nodes (``bench/cluster.py``'s), when Ray is installed.

    .venv/bin/python bench/benchmark.py [--benchmark dmc-classic] [--ways local,cluster] [--json]
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx

sys.path.insert(0, str(Path(__file__).resolve().parent))
from cluster import SLOTS, Served, loopback_cluster
from evaluate import busy_seconds

from labd.sim.simulation import Simulation

ROOT = Path(__file__).resolve().parent.parent
STILL = '''\
"""Step every tick and send nothing: every task's actions stay zero."""
from controllers.client import EpisodeOver, Lab

with Lab.connect() as lab:
    try:
        while True:
            lab.step()
    except EpisodeOver:
        pass
'''


def repository(folder: Path) -> Path:
    folder.mkdir(parents=True)
    (folder / "lab.toml").write_text(
        '[controller]\ncommand = ["python", "c.py"]\ntask = "dmc-cartpole-balance"\n'
    )
    (folder / "c.py").write_text(STILL)
    git = ["git", "-C", str(folder), "-c", "user.name=bench", "-c", "user.email=bench@example.org"]
    subprocess.run([*git, "init", "-q", "-b", "main"], check=True)
    subprocess.run([*git, "add", "-A"], check=True)
    subprocess.run([*git, "commit", "-qm", "a controller that sends nothing"], check=True)
    return folder


def run(served: Served, repo: Path, benchmark: str) -> tuple[dict[str, Any], float, float]:
    """Submit a benchmark run and follow it to its last replay's verdict: the run, its
    seconds, and the machine's busy CPU seconds meanwhile."""
    headers = {"Authorization": f"Bearer {served.token}"}
    busy_before = busy_seconds()[0]
    with httpx.Client(base_url=served.server, headers=headers, timeout=120) as client:
        started = time.monotonic()
        answer = client.post(
            "/api/benchmark-runs", json={"repository": str(repo), "benchmark": benchmark}
        )
        answer.raise_for_status()
        made = answer.json()
        deadline = time.monotonic() + 3600
        while True:
            made = client.get(f"/api/benchmark-runs/{made['id']}").json()
            print(f"[bench]   {made['done']}/{made['episodes']}", end="\r", file=sys.stderr)
            if made["status"] in ("finished", "cancelled"):
                rows = [
                    r
                    for task in made["evaluations"]
                    for r in client.get(f"/api/evaluations/{task['evaluation']}").json()["rows"]
                ]
                if all(r["verified"] is not None for r in rows):
                    break
            if time.monotonic() > deadline:
                raise RuntimeError("the run did not end:\n" + "".join(served.output[-40:]))
            time.sleep(1.0)
        seconds = time.monotonic() - started
        made = client.get(f"/api/benchmark-runs/{made['id']}").json()  # with the last verdicts
        episodes = [
            (task["task"], r["seed"], client.get(f"/api/trials/{r['trial']}").json())
            for task in made["evaluations"]
            for r in client.get(f"/api/evaluations/{task['evaluation']}").json()["rows"]
        ]
    print(file=sys.stderr)
    made["_episodes"] = [(task, seed, t["metrics"]["ticks"]) for task, seed, t in episodes]
    return made, seconds, busy_seconds()[0] - busy_before


def physics_alone(episodes: list[tuple[str, int, int]]) -> float:
    """Seconds to step the same episodes' ticks in this process, no controller, no record."""
    total = 0.0
    for task, seed, ticks in episodes:
        sim = Simulation(task, {}, seed)
        started = time.perf_counter()
        for _ in range(ticks):
            sim.env.step(sim.task.action(sim.physics))
        total += time.perf_counter() - started
    return total


@contextlib.contextmanager
def ways(names: list[str]) -> Iterator[dict[str, tuple[str, ...]]]:
    found: dict[str, tuple[str, ...]] = {}
    if "local" in names:
        found["local"] = ("--workers", str(SLOTS))
    if "cluster" not in names:
        yield found
        return
    try:
        import ray  # noqa: F401, PLC0415 (labd[cluster]'s: only for this way)
    except ImportError:
        print("[bench] no Ray here: the cluster way is left out", file=sys.stderr)
        yield found
        return
    with loopback_cluster() as address:
        found["cluster"] = ("--workers", "0", "--ray-address", address)
        yield found


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--benchmark", default="dmc-classic")
    parser.add_argument("--ways", default="local,cluster", help="local, cluster or both")
    parser.add_argument("--cache", type=Path, default=ROOT / "lab-data" / "cache")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    args.cache.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix="bench-benchmark-"))
    work.chmod(0o755)
    repo = repository(work / "still")
    results: dict[str, Any] = {"benchmark": args.benchmark, "cpus": os.cpu_count(), "ways": {}}
    episodes: list[tuple[str, int, int]] = []
    try:
        with ways(args.ways.split(",")) as found:
            for way, extra in found.items():
                print(f"[bench] {way}", file=sys.stderr)
                served = Served(work / f"data-{way}", args.cache, *extra)
                try:
                    made, seconds, busy = run(served, repo, args.benchmark)
                finally:
                    served.stop()
                episodes = episodes or made["_episodes"]
                n = made["episodes"]
                results["ways"][way] = {
                    "seconds": round(seconds, 1),
                    "episodes": n,
                    "verified": made["verified"],
                    "iqm": made["iqm"],
                    "cpu_seconds_per_episode": round(busy / n, 3),
                    "cores_busy": round(busy / seconds, 2),
                }
        physics = physics_alone(episodes)
        results["physics_seconds_per_episode"] = round(physics / len(episodes), 4)
        for row in results["ways"].values():
            row["cpu_to_physics"] = round(
                row["cpu_seconds_per_episode"] / results["physics_seconds_per_episode"], 1
            )
    finally:
        shutil.rmtree(work, ignore_errors=True)
    if args.json:
        print(json.dumps(results, indent=2))
        return
    print(f"A {args.benchmark} run of a controller that sends nothing, through labd serve")
    print(f"  ({results['cpus']} CPUs; seconds from submitting to the last replay's verdict)\n")
    print(f"  {'':10} {'seconds':>8} {'episodes':>9} {'CPU s/episode':>14} {'x physics':>10}")
    for way, row in results["ways"].items():
        print(
            f"  {way:10} {row['seconds']:8.1f} {row['episodes']:9d}"
            f" {row['cpu_seconds_per_episode']:14.2f} {row['cpu_to_physics']:10.1f}"
            f"   verified {row['verified']}, cores busy {row['cores_busy']}"
        )
    print(f"\n  the physics alone: {results['physics_seconds_per_episode']:.3f} s an episode")


if __name__ == "__main__":
    main()
