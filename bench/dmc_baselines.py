"""The dm_control pack's floor: what doing nothing, or flailing, earns on the dev seeds.

For every pack task and each dev seed (0 to 19), one full episode of dm_control's own
environment with zero actions and one with uniform random actions (numpy's default
generator seeded with the episode's seed), and prints per task the mean and the best
return of each, and how many episodes reach the task's threshold. docs/tasks.md quotes
these numbers beside each threshold: a threshold is only meaningful well above them.

    .venv/bin/python bench/dmc_baselines.py [--seeds N] [--task NAME ...] [--json]
"""

from __future__ import annotations

import argparse
import json
from typing import Any

import numpy as np
from dm_control import suite

from labd.sim.dmc import CATALOG, Listing


def episode_return(listing: Listing, seed: int, policy: str) -> float:
    env = suite.load(listing.domain, listing.task, task_kwargs={"random": seed})
    spec = env.action_spec()
    rng = np.random.default_rng(seed)
    timestep = env.reset()
    total = 0.0
    while not timestep.last():
        if policy == "zero":
            action = np.zeros(spec.shape)
        else:
            action = rng.uniform(spec.minimum, spec.maximum, spec.shape)
        timestep = env.step(action)
        total += float(timestep.reward)
    return total


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=20, help="dev seeds 0 .. N-1")
    parser.add_argument("--task", action="append", help="only these tasks (dmc-...)")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    rows: dict[str, Any] = {}
    for listing in CATALOG:
        if args.task and listing.name not in args.task:
            continue
        row: dict[str, Any] = {"threshold": listing.threshold}
        for policy in ("zero", "random"):
            returns = [episode_return(listing, s, policy) for s in range(args.seeds)]
            row[policy] = {
                "mean": float(np.mean(returns)),
                "max": float(np.max(returns)),
                "solved": sum(r >= listing.threshold for r in returns),
            }
        rows[listing.name] = row
        if not args.json:
            zero, rand = row["zero"], row["random"]
            print(
                f"{listing.name:28} threshold {listing.threshold:5.0f}   "
                f"zero {zero['mean']:5.0f} (max {zero['max']:4.0f}, {zero['solved']:2d} solved)   "
                f"random {rand['mean']:5.0f} (max {rand['max']:4.0f}, {rand['solved']:2d} solved)",
                flush=True,
            )
    if args.json:
        print(json.dumps(rows, indent=2))


if __name__ == "__main__":
    main()
