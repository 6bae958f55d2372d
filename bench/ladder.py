"""The ladder's fit and bootstrap against a plain numpy baseline, on a made-up ladder.

    .venv/bin/python bench/ladder.py [--entries 50] [--legs 500] [--resamples 1000]

The ladder: entries of Bradley-Terry strengths drawn around 0 (sd 300 points), matches of
two legs between random pairs, a leg a draw one time in five. ``repository.ladder.ladder``
fits every resample at once (Newton's method on a stack of them); the baseline fits one
resample after another, each by Newton's method on its legs (no summing by pair), in numpy
too, from the same draws of matches. Prints both times, their ratio, and how far apart the
two sets of intervals are (they solve the same problem: a few 1e-6 points at most).
"""

from __future__ import annotations

import argparse
import math
import random
import time

import numpy as np

from repository.ladder import CENTRE, PRIOR_SD, Leg, ladder


def made_up(entries: int, legs: int, seed: int) -> list[Leg]:
    rng = random.Random(seed)
    strength = [rng.gauss(0, 300) for _ in range(entries)]
    played = []
    for m in range(legs // 2):
        a, b = rng.sample(range(entries), 2)
        p = 1 / (1 + 10 ** ((strength[b] - strength[a]) / 400))
        for _ in range(2):
            score = 0.5 if rng.random() < 0.2 else float(rng.random() < p)
            played.append(Leg(f"m{m}", f"e{a}", f"e{b}", score))
    return played


def baseline(legs: list[Leg], resamples: int, seed: int) -> np.ndarray:
    """Each entry's 2.5th and 97.5th percentile, fitting resamples one at a time."""
    entries = sorted({leg.a for leg in legs} | {leg.b for leg in legs})
    matches = sorted({leg.match for leg in legs})
    index = {e: k for k, e in enumerate(entries)}
    match_of = np.array([matches.index(leg.match) for leg in legs])
    design = np.zeros((len(legs), len(entries)))  # +1 for a, -1 for b
    design[np.arange(len(legs)), [index[leg.a] for leg in legs]] = 1
    design[np.arange(len(legs)), [index[leg.b] for leg in legs]] = -1
    y = np.array([leg.score for leg in legs])
    scale, precision = math.log(10) / 400, 1 / (PRIOR_SD * math.log(10) / 400) ** 2
    rng = np.random.default_rng(seed)
    ratings = []
    for _ in range(resamples):
        weight = np.bincount(rng.integers(0, len(matches), len(matches)), minlength=len(matches))
        w = weight[match_of].astype(float)
        theta = np.zeros(len(entries))
        for _ in range(100):
            p = 1 / (1 + np.exp(-(design @ theta)))
            gradient = design.T @ (w * (y - p)) - precision * theta
            hessian = (design.T * (w * p * (1 - p))) @ design + precision * np.eye(len(entries))
            step = np.linalg.solve(hessian, gradient)
            theta += step
            if np.abs(step).max() < 1e-10:
                break
        ratings.append(CENTRE + theta / scale)
    return np.quantile(np.array(ratings), [0.025, 0.975], axis=0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--entries", type=int, default=50)
    parser.add_argument("--legs", type=int, default=500)
    parser.add_argument("--resamples", type=int, default=1000)
    args = parser.parse_args()
    legs = made_up(args.entries, args.legs, seed=0)

    start = time.perf_counter()
    rows = ladder(legs, resamples=args.resamples)
    batched = time.perf_counter() - start
    start = time.perf_counter()
    ends = baseline(legs, args.resamples, seed=0)
    plain = time.perf_counter() - start

    entries = sorted({leg.a for leg in legs} | {leg.b for leg in legs})
    by_entry = {row.entry: row.interval for row in rows}
    apart = max(
        abs(by_entry[e][0] - ends[0, k]) + abs(by_entry[e][1] - ends[1, k])
        for k, e in enumerate(entries)
    )
    print(f"{args.entries} entries, {len(legs)} legs, {args.resamples} resamples")
    print(f"ladder (batched):      {batched:7.3f} s")
    print(f"baseline (one by one): {plain:7.3f} s   ratio {plain / batched:5.1f}x")
    print(f"intervals apart by at most {apart:.2e} points")


if __name__ == "__main__":
    main()
