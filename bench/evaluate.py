"""What an evaluation costs: episodes per hour through `labd serve`, against the physics.

A 50-episode evaluation of the maze example controller (``controllers/examples/
icreate-maze``, on the maze's held-out ``test`` suite: 50 mazes) runs through a real
``labd serve`` with 1 and then 2 bubblewrap workers, submitted and followed as a user
does (``labd evaluate``'s API), with the lab's defaults (every record replayed to verify
it; videos rendered in the background at the lowest priority). For each it prints
episodes per hour, from submitting to the last episode's replay verdict, and the ratio
to the limit: the same episodes' ticks stepped in-process with no controller, no
sandbox, no recording (the physics alone, in this process, one core).

Then where one episode's wall time goes, as medians over the episodes of the 1-worker
run: from the index's times (claimed, filed, its summary and replay made) and the
trial's own figures (the time to the first ``/lab/step``, the ticks), and one episode
run again in this process through the trial runner, to split preparing (checkout,
lab.toml, the sandbox's set-up) from the sandbox and controller start.

    .venv/bin/python bench/evaluate.py [--suite test] [--workers 1,2] [--json]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import httpx
import sqlalchemy as sa

import sandbox
from labd.sim.simulation import Simulation
from labd.trial import LabHost, client_library
from repository.tables import derived, episodes, trials
from repository.trial import Order
from repository.well_known import REPLAY, SUMMARY
from scheduler.runner import RunOptions, run_trial

ROOT = Path(__file__).resolve().parent.parent
EXAMPLE = ROOT / "controllers" / "examples" / "icreate-maze"


def repository(folder: Path) -> Path:
    """The example controller as a git repository of its own."""
    shutil.copytree(EXAMPLE, folder)
    git = ["git", "-C", str(folder), "-c", "user.name=bench", "-c", "user.email=bench@example.org"]
    subprocess.run([*git, "init", "-q", "-b", "main"], check=True)
    subprocess.run([*git, "add", "-A"], check=True)
    subprocess.run([*git, "commit", "-qm", "the maze example"], check=True)
    return folder


class Served:
    """`labd serve` on a data folder of its own, with ``workers`` bubblewrap workers."""

    def __init__(self, data: Path, cache: Path, workers: int, videos: str, processes: bool) -> None:
        self.data = data
        env = {**os.environ}
        data.mkdir(parents=True)
        made = subprocess.run(
            [sys.executable, "-m", "labd", "users", "add", "bench", "--data", str(data),
             "--max-running", str(workers), "--json"],
            capture_output=True, text=True, check=True,
        )  # fmt: skip
        self.token = json.loads(made.stdout)["token"]
        self.process = subprocess.Popen(
            [sys.executable, "-m", "labd", "serve", "--data", str(data), "--cache", str(cache),
             "--http-port", "0", "--bridge-port", "0", "--no-robots",
             *(["--workers", "0", "--worker-processes", str(workers)] if processes
               else ["--workers", str(workers)]),
             "--sandbox", "bwrap", "--allow-local-repos", "--videos", videos],
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env,
        )  # fmt: skip
        assert self.process.stdout is not None
        for line in self.process.stdout:
            found = re.search(r"HTTP API on (http://\S+?)/api", line)
            if found:
                self.server = found.group(1)
                break
        else:
            raise RuntimeError("labd serve did not start")

    def stop(self) -> None:
        self.process.terminate()
        self.process.wait(60)


def busy_seconds() -> tuple[float, float]:
    """The machine's CPU seconds spent busy and in all, summed over its cores
    (``/proc/stat``: everything but idle and I/O wait is busy)."""
    fields = [int(v) for v in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]
    tick = os.sysconf("SC_CLK_TCK")
    idle = fields[3] + fields[4]
    return (sum(fields) - idle) / tick, sum(fields) / tick


def evaluate(served: Served, repo: Path, suite: str) -> tuple[dict[str, Any], float, float]:
    """Submit an evaluation and follow it until its episodes are filed and replayed; the
    evaluation, and the seconds from submitting to its last episode filed and to its last
    replay's verdict."""
    headers = {"Authorization": f"Bearer {served.token}"}
    with httpx.Client(base_url=served.server, headers=headers, timeout=120) as client:
        started = time.monotonic()
        answer = client.post("/api/evaluations", json={"repository": str(repo), "suite": suite})
        answer.raise_for_status()
        evaluation = answer.json()
        while evaluation["status"] not in ("finished", "cancelled"):
            time.sleep(0.5)
            evaluation = client.get(f"/api/evaluations/{evaluation['id']}").json()
            score = evaluation
            print(f"[bench]   {score['done']}/{score['episodes']} done", end="\r", file=sys.stderr)
        filed = time.monotonic() - started
        while any(r["verified"] is None for r in evaluation["rows"]):  # the last replays
            time.sleep(0.2)
            evaluation = client.get(f"/api/evaluations/{evaluation['id']}").json()
        verified = time.monotonic() - started
    print(file=sys.stderr)
    return evaluation, filed, verified


def stages(data: Path, evaluation_id: int) -> dict[str, float]:
    """Median seconds of each stage of an episode, from the index's times."""
    engine = sa.create_engine(f"sqlite:///{data / 'index.sqlite'}")
    made = {}
    with engine.connect() as db:
        rows = db.execute(
            sa.select(trials.c.id, trials.c.started, trials.c.finished, trials.c.wall_seconds)
            .join(episodes, episodes.c.trial_id == trials.c.id)
            .where(episodes.c.evaluation_id == evaluation_id)
        ).all()
        for r in db.execute(sa.select(derived.c.trial_id, derived.c.name, derived.c.created)):
            made[r.trial_id, r.name] = r.created
    engine.dispose()
    run = [r.wall_seconds for r in rows]
    filing = [r.finished - r.started - r.wall_seconds for r in rows]
    summary = [made[r.id, SUMMARY] - r.finished for r in rows if (r.id, SUMMARY) in made]
    replay = [
        made[r.id, REPLAY] - made[r.id, SUMMARY]
        for r in rows
        if (r.id, REPLAY) in made and (r.id, SUMMARY) in made
    ]
    return {
        "run (checkout to the record written)": statistics.median(run),
        "filing (the record checked, stored, signed)": statistics.median(filing),
        "summary (for its page)": statistics.median(summary),
        "replay (re-simulated, compared)": statistics.median(replay),
    }


def one_episode(cache: Path, repo: Path, seed: int) -> dict[str, float]:
    """One episode through the trial runner in this process: prepare, start, ticks."""
    backend = sandbox.backend("bwrap", cache, extra_packages=[client_library()])
    out = Path(tempfile.mkdtemp(prefix="bench-episode-"))
    order = Order(repository=str(repo), ref="main", task="icreate-maze", seed=seed)
    result = asyncio.run(
        run_trial(
            order, backend=backend, host=LabHost(), out=out, cache=cache, options=RunOptions()
        )
    )
    shutil.rmtree(out, ignore_errors=True)
    assert result.start_seconds is not None and result.run_seconds is not None
    ticks = int(result.metrics["ticks"])
    return {
        "prepare (checkout, lab.toml, sandbox set-up)": result.wall_seconds
        - result.start_seconds
        - result.run_seconds,
        "sandbox and controller start (to the first /lab/step)": result.start_seconds,
        "ticks (lockstep, recorded)": result.run_seconds,
        "ms per tick": 1000 * result.run_seconds / ticks,
    }


def physics_alone(seeds: list[int], ticks: list[int]) -> float:
    """Seconds to step the same episodes' ticks in-process, no controller, no recording."""
    total = 0.0
    for seed, count in zip(seeds, ticks, strict=True):
        sim = Simulation("icreate-maze", {}, seed)
        started = time.perf_counter()
        for _ in range(count):
            sim.env.step(sim.task.action(sim.physics))
        total += time.perf_counter() - started
    return total


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--suite", default="test", help="the maze's suite (default: test, 50)")
    parser.add_argument("--workers", default="1,2", help="worker counts (default: 1,2)")
    parser.add_argument("--cache", type=Path, default=ROOT / "lab-data" / "cache")
    parser.add_argument(
        "--videos", default="background", help="labd serve --videos (default: background)"
    )
    parser.add_argument(
        "--processes",
        action="store_true",
        help="the workers in processes of their own (labd serve --worker-processes)",
    )
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    args.cache.mkdir(parents=True, exist_ok=True)
    sandbox.backend("bwrap", args.cache, extra_packages=[client_library()])  # built once
    work = Path(tempfile.mkdtemp(prefix="bench-evaluate-"))
    work.chmod(0o755)
    repo = repository(work / "maze")
    results: dict[str, Any] = {
        "suite": args.suite,
        "videos": args.videos,
        "processes": args.processes,
        "runs": {},
    }
    seeds: list[int] = []
    ticks: list[int] = []
    try:
        for workers in [int(w) for w in args.workers.split(",")]:
            print(f"[bench] {workers} worker(s)", file=sys.stderr)
            served = Served(
                work / f"data-{workers}", args.cache, workers, args.videos, args.processes
            )
            busy_before, _ = busy_seconds()
            try:
                evaluation, filed, elapsed = evaluate(served, repo, args.suite)
                busy = busy_seconds()[0] - busy_before
            finally:
                served.stop()
            score = evaluation
            run: dict[str, Any] = {
                "seconds": round(elapsed, 1),  # to the last verdict
                "filed_seconds": round(filed, 1),
                "episodes_per_hour": round(3600 * score["episodes"] / elapsed),
                "success_rate": score["success_rate"],
                "verified": score["verified"],
                # the whole machine's CPU while it ran: what an episode costs, and how
                # many cores were busy on average (2 of 2: the machine was full)
                "cpu_seconds_per_episode": round(busy / score["episodes"], 3),
                "cores_busy": round(busy / elapsed, 2),
            }
            results["episodes"] = score["episodes"]
            if not ticks:  # the episodes' seeds (the operator's, read here) and ticks
                engine = sa.create_engine(f"sqlite:///{served.data / 'index.sqlite'}")
                with engine.connect() as db:
                    found = db.execute(
                        sa.select(episodes.c.seed, trials.c.metrics)
                        .join(trials, episodes.c.trial_id == trials.c.id)
                        .order_by(episodes.c.episode)
                    ).all()
                engine.dispose()
                seeds = [int(seed) for seed, _ in found]
                ticks = [int(metrics["ticks"]) for _, metrics in found]
                run["stages"] = stages(served.data, evaluation["id"])
            results["runs"][workers] = run
        physics = physics_alone(seeds, ticks)
        results["physics_seconds"] = round(physics, 1)
        results["physics_episodes_per_hour"] = round(3600 * len(seeds) / physics)
        for run in results["runs"].values():
            run["ratio_to_physics"] = round(physics / run["seconds"], 3)
        results["one_episode"] = one_episode(args.cache, repo, seed=seeds[0])
    finally:
        shutil.rmtree(work, ignore_errors=True)
    if args.json:
        print(json.dumps(results, indent=2))
        return
    report(results)


def report(results: dict[str, Any]) -> None:
    n, suite = results["episodes"], results["suite"]
    print(f"A {n}-episode maze evaluation (suite {suite}) of the example controller, labd serve")
    print(f"  (bubblewrap; each episode summarized and replayed; {os.cpu_count()} CPUs;")
    print("  seconds from submitting to the last replay's verdict)\n")
    print(
        f"  {'':22} {'seconds':>8} {'episodes/h':>11} {'of the limit':>13}  rate  verified"
        "  CPU s/episode  cores busy"
    )
    for workers, r in results["runs"].items():
        print(
            f"  {workers} worker(s){'':12} {r['seconds']:8.1f} {r['episodes_per_hour']:11d}"
            f" {r['ratio_to_physics']:12.1%}  {r['success_rate']:.0%}  {r['verified']!s:8}"
            f" {r['cpu_seconds_per_episode']:13.2f} {r['cores_busy']:11.2f}"
        )
    print(
        f"  {'the physics alone':22} {results['physics_seconds']:8.1f}"
        f" {results['physics_episodes_per_hour']:11d} {'(the limit)':>13}\n"
    )
    print("Where one episode's time goes (medians, 1 worker):")
    for stage, seconds in next(iter(results["runs"].values()))["stages"].items():
        print(f"  {stage:55} {seconds:7.2f} s")
    print("One episode in this process, through the trial runner:")
    for stage, value in results["one_episode"].items():
        unit = "ms" if stage.startswith("ms") else "s"
        print(f"  {stage:55} {value:7.2f} {unit}")


if __name__ == "__main__":
    main()
