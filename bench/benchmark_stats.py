"""A benchmark run's aggregate and probability of improvement against a plain Python loop.

    .venv/bin/python bench/benchmark_stats.py [--tasks 26] [--episodes 20] [--resamples 2000]

Two made-up runs of normalized scores (A a little better than B). ``aggregate`` and
``probability_of_improvement`` draw every resample at once; the baseline draws one resample
after another in pure Python (``random.choices`` per task, ``statistics`` for the IQM, mean
and median, pairs counted one by one), measured in the same run. Prints both times, their
ratio, and how far apart the intervals are: other draws, so Monte Carlo noise of about a
hundredth, no more.
"""

from __future__ import annotations

import argparse
import random
import statistics
import time

from repository.benchmark_stats import aggregate, iqm, probability_of_improvement


def made_up(tasks: int, episodes: int, power: float, seed: int) -> list[list[float]]:
    rng = random.Random(seed)
    return [[rng.random() ** power for _ in range(episodes)] for _ in range(tasks)]


def percentiles(values: list[float]) -> tuple[float, float]:
    cuts = statistics.quantiles(values, n=40, method="inclusive")  # 2.5 % steps
    return cuts[0], cuts[-1]


def baseline_aggregate(
    per_task: list[list[float]], resamples: int, seed: int
) -> list[tuple[float, float]]:
    rng = random.Random(seed)
    iqms, means, medians = [], [], []
    for _ in range(resamples):
        pool = [score for task in per_task for score in rng.choices(task, k=len(task))]
        iqms.append(iqm(pool))
        means.append(statistics.fmean(pool))
        medians.append(statistics.median(pool))
    return [percentiles(iqms), percentiles(means), percentiles(medians)]


def baseline_improvement(
    a: list[list[float]], b: list[list[float]], resamples: int, seed: int
) -> tuple[float, float]:
    rng = random.Random(seed)
    drawn = []
    for _ in range(resamples):
        total = 0.0
        for x, y in zip(a, b, strict=True):
            xs, ys = rng.choices(x, k=len(x)), rng.choices(y, k=len(y))
            wins = sum((p > q) + 0.5 * (p == q) for p in xs for q in ys)
            total += wins / (len(xs) * len(ys))
        drawn.append(total / len(a))
    return percentiles(drawn)


def report(batched: float, plain: float, apart: float) -> None:
    print(f"  vectorised {batched * 1000:8.1f} ms   python loop {plain * 1000:8.1f} ms", end="")
    print(f"   ratio {plain / batched:6.1f}x   intervals at most {apart:.4f} apart")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--tasks", type=int, default=26)
    parser.add_argument("--episodes", type=int, default=20)
    parser.add_argument("--resamples", type=int, default=2000)
    args = parser.parse_args()
    a = made_up(args.tasks, args.episodes, 0.8, seed=0)
    b = made_up(args.tasks, args.episodes, 1.0, seed=1)
    aggregate([[0.5]], resamples=1)  # numpy's import is not the bootstrap's time

    start = time.perf_counter()
    fast = aggregate(a, resamples=args.resamples)
    batched = time.perf_counter() - start
    start = time.perf_counter()
    slow = baseline_aggregate(a, args.resamples, seed=0)
    plain = time.perf_counter() - start
    ours = [fast.iqm_interval, fast.mean_interval, fast.median_interval]
    apart = max(
        abs(x - y)
        for got, want in zip(ours, slow, strict=True)
        for x, y in zip(got, want, strict=True)
    )
    print(f"aggregate, {args.tasks} tasks x {args.episodes} episodes x {args.resamples} resamples:")
    report(batched, plain, apart)

    start = time.perf_counter()
    improvement = probability_of_improvement(a, b, resamples=args.resamples)
    batched = time.perf_counter() - start
    start = time.perf_counter()
    ends = baseline_improvement(a, b, args.resamples, seed=0)
    plain = time.perf_counter() - start
    apart = max(abs(x - y) for x, y in zip(improvement.interval, ends, strict=True))
    print(f"probability of improvement {improvement.probability:.3f} {improvement.interval}:")
    report(batched, plain, apart)


if __name__ == "__main__":
    main()
