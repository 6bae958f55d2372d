"""A controller in JavaScript against the same in Python: start and time per tick.

The maze examples, ``controllers/examples/icreate-maze-js`` (Node.js, roslibjs) and
``controllers/examples/icreate-maze`` (Python, the lab's client library), run the same
seeds through the same trial runner in each sandbox. For each: the start latency (from
starting the controller to its first ``/lab/step``: the runtime, imports, connecting)
and the time per control tick, medians over the seeds, and the ratios of JavaScript to
Python. Targets (from the issue): JavaScript's start under 1 s, its tick within 1.2
times Python's. The two solvers make the same decisions from the same messages, so a
seed takes them about the same number of ticks; each is deterministic (the same data
digest in both sandboxes).

    .venv/bin/python bench/javascript.py [--seeds 0,1,2,3] [--json]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path
from typing import Any

import sandbox
from labd.trial import client_library

sys.path.insert(0, str(Path(__file__).resolve().parent))
from trial import ROOT, trials

EXAMPLES = {
    "python": ROOT / "controllers" / "examples" / "icreate-maze",
    "javascript": ROOT / "controllers" / "examples" / "icreate-maze-js",
}
START = 1.0  # s, JavaScript's start, at most
TICK_RATIO = 1.2  # JavaScript's time per tick over Python's, at most


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", default="0,1,2,3")
    parser.add_argument("--cache", type=Path, default=ROOT / "lab-data" / "cache")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    seeds = [int(s) for s in args.seeds.split(",")]
    args.cache.mkdir(parents=True, exist_ok=True)
    results: dict[str, Any] = {}
    for name in ("bwrap", "docker"):
        try:
            backend = sandbox.backend(name, args.cache, extra_packages=[client_library()])
        except sandbox.BackendUnavailable as err:
            print(f"[bench] {name}: {err}", file=sys.stderr)
            continue
        figures: dict[str, Any] = {}
        for language, example in EXAMPLES.items():
            print(f"[bench] {name}: {language}", file=sys.stderr)
            runs = trials(backend, seeds, args.cache, example)
            figures[language] = {
                "start_s_median": statistics.median(r["start"] for r in runs),
                "per_tick_ms_median": statistics.median(r["per_tick_ms"] for r in runs),
                "ticks": [r["ticks"] for r in runs],
                "digests": [r["digest"] for r in runs],
            }
        js, py = figures["javascript"], figures["python"]
        figures["tick_ratio"] = js["per_tick_ms_median"] / py["per_tick_ms_median"]
        figures["start_ratio"] = js["start_s_median"] / py["start_s_median"]
        results[name] = figures
    if len(results) == 2:
        a, b = (results[n]["javascript"]["digests"] for n in ("bwrap", "docker"))
        results["same_data_across_sandboxes"] = a == b
    if args.json:
        print(json.dumps(results, indent=2))
        return
    report(results, seeds)


def report(results: dict[str, Any], seeds: list[int]) -> None:
    print("The maze example in JavaScript (Node.js, roslibjs) against Python, in each sandbox")
    print(f"  seeds {','.join(map(str, seeds))}; medians over the seeds; 2 CPUs\n")
    print(f"  {'':8} {'':11} {'start':>8} {'per tick':>10}  ticks")
    for name in ("bwrap", "docker"):
        if name not in results:
            continue
        for language in ("python", "javascript"):
            f = results[name][language]
            print(
                f"  {name:8} {language:11} {f['start_s_median']:7.2f}s"
                f" {f['per_tick_ms_median']:8.2f}ms  {','.join(map(str, f['ticks']))}"
            )
        f = results[name]
        print(f"  {name:8} {'JS / Py':11} {f['start_ratio']:7.2f}x {f['tick_ratio']:9.2f}x")
    print()
    for name in ("bwrap", "docker"):
        if name not in results:
            print(f"  SKIP  {name}: not available")
            continue
        js = results[name]["javascript"]
        ok_start = js["start_s_median"] < START
        ok_tick = results[name]["tick_ratio"] <= TICK_RATIO
        print(f"  {'PASS' if ok_start else 'FAIL'}  {name}: JavaScript's start < {START:g} s")
        print(
            f"  {'PASS' if ok_tick else 'FAIL'}  {name}: JavaScript's tick <= {TICK_RATIO}x"
            " Python's"
        )
    if "same_data_across_sandboxes" in results:
        same = results["same_data_across_sandboxes"]
        print(f"  {'PASS' if same else 'FAIL'}  JavaScript: the same data in both sandboxes")


if __name__ == "__main__":
    main()
