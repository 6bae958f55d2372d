"""What a leg of a match costs against a trial of one of its teams alone.

The ball chaser (``controllers/examples/soccer-chaser``) plays ``soccer-1v1`` on each
seed three ways, in bubblewrap, in this process, alternating so the machine's load
falls on each alike:

- **alone**: one trial through the trial runner (``run_trial``): the away side stands
  still;
- **against the still team**: a leg (``run_leg``) against ``controllers/examples/
  soccer-still``, which steps and never moves: the same game as alone, tick for tick,
  with a second sandbox and the shared tick;
- **against itself**: a leg of two chasers.

For each it prints the medians of the wall time, the time in ticks (first step to the
end) per tick, and the ratio of a leg's per-tick time to the lone trial's. A leg pays
for a second controller (its process, its messages) and for the barrier (each tick
waits for the slower team).

    .venv/bin/python bench/match.py [--seeds 2,7] [--rounds 2] [--json]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import shutil
import statistics
import tempfile
from pathlib import Path
from typing import Any

import sandbox
from labd.trial import LabHost, client_library
from repository.trial import Order
from scheduler.leg import run_leg
from scheduler.runner import TrialResult, run_trial

ROOT = Path(__file__).resolve().parent.parent
EXAMPLES = ROOT / "controllers" / "examples"
CHASER, STILL = EXAMPLES / "soccer-chaser", EXAMPLES / "soccer-still"
TASK = "soccer-1v1"


def run(way: str, seed: int, cache: Path) -> TrialResult:
    backend = sandbox.backend("bwrap", cache, extra_packages=[client_library()])
    out = Path(tempfile.mkdtemp(prefix="bench-match-"))
    home = Order(repository=str(CHASER), task=TASK, seed=seed)
    try:
        if way == "alone":
            coro = run_trial(home, backend=backend, host=LabHost(), out=out, cache=cache)
        else:
            away = Order(repository=str(STILL if way == "still" else CHASER), task=TASK, seed=seed)
            orders = {"home": home, "away": away}
            coro = run_leg(orders, backend=backend, host=LabHost(), out=out, cache=cache)
        result = asyncio.run(coro)
    finally:
        shutil.rmtree(out, ignore_errors=True)
    if result.run_seconds is None:
        raise SystemExit(f"{way}, seed {seed}: {result.reason}")
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", default="2,7", help="comma-separated seeds")
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--cache", type=Path, default=ROOT / ".pytest_cache/d/labd-trials")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    seeds = [int(s) for s in args.seeds.split(",")]
    ways = ("alone", "still", "itself")
    found: dict[str, dict[str, list[float]]] = {w: {"wall": [], "tick_ms": []} for w in ways}
    ticks: dict[tuple[str, int], int] = {}
    for _ in range(args.rounds):
        for seed in seeds:
            for way in ways:
                result = run(way, seed, args.cache.resolve())
                count = int(result.metrics["ticks"])
                ticks[(way, seed)] = count
                found[way]["wall"].append(result.wall_seconds)
                assert result.run_seconds is not None
                found[way]["tick_ms"].append(1000 * result.run_seconds / count)
    report: dict[str, Any] = {"seeds": seeds, "rounds": args.rounds, "ways": {}}
    base = statistics.median(found["alone"]["tick_ms"])
    for way in ways:
        tick_ms = statistics.median(found[way]["tick_ms"])
        report["ways"][way] = {
            "wall_seconds": round(statistics.median(found[way]["wall"]), 2),
            "ms_per_tick": round(tick_ms, 3),
            "per_tick_vs_alone": round(tick_ms / base, 2),
            "ticks": {str(s): ticks[(way, s)] for s in seeds},
        }
    if args.json:
        print(json.dumps(report, indent=2))
        return
    print(f"soccer-1v1, the ball chaser, seeds {seeds}, {args.rounds} rounds (medians)")
    for way, row in report["ways"].items():
        print(
            f"  {way:7} wall {row['wall_seconds']:6.2f} s   {row['ms_per_tick']:6.3f} ms a tick"
            f"   {row['per_tick_vs_alone']:4.2f}x alone's   ticks {row['ticks']}"
        )


if __name__ == "__main__":
    main()
