"""The statistics of a benchmark run: how one controller did over many tasks, and whether it
beats another, as the field reports it (rliable: Agarwal et al., "Deep Reinforcement
Learning at the Edge of the Statistical Precipice", NeurIPS 2021).

A benchmark run scores a controller on several tasks, each a list of its episodes'
normalized scores in [0, 1]. The statistics follow the paper's definitions, written here
from them (rliable itself is archived):

- the **interquartile mean** (``iqm``): the mean of the middle 50 % of the scores, a
  quarter cut at each end, exactly as ``scipy.stats.trim_mean(scores, 0.25)`` cuts it
  (``int(0.25 * n)`` from each end of the sorted scores). Like the median it ignores the
  few episodes that crash to 0 or fluke to 1; unlike the median it averages half the
  episodes rather than one or two, so it varies less from sample to sample;
- the **aggregate** (``aggregate``): the IQM, mean and median over every episode's score
  pooled, each with a 95 % percentile interval from a **stratified bootstrap**: a resample
  draws, for each task on its own, as many episodes as that task has, with replacement
  from that task's episodes. Every task keeps its weight in every resample, so the
  interval measures how the episodes vary, not how a plain bootstrap happens to draw
  more of the easy tasks one time and more of the hard ones the next;
- the **performance profile** (``profile``): for each threshold τ, the fraction of all
  episodes scoring strictly above τ; a curve that lies above another everywhere is
  better at every level of demand (stochastic dominance);
- the **probability of improvement** (``probability_of_improvement``): the chance that an
  episode of A scores above one of B on the same task, ties counting half (the
  Mann-Whitney U statistic over n · m), averaged over tasks with equal weight, with a
  stratified bootstrap interval that resamples each task's episodes of A and of B
  independently. It says how often A is better, not by how much.

Pooled statistics weigh each task by its episodes; the paper's matrix of runs by tasks gives
every task the same number. Every bootstrap draws from a generator seeded with ``seed``,
so the same scores always give the same intervals: a report can be recomputed and
checked. Only the bootstraps need numpy, and import it when they run.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import numpy as np
    from numpy.typing import NDArray

    Array = NDArray[np.float64]

RESAMPLES = 2000  # bootstrap resamples by default, as repository.stats draws
LEVEL = 0.95  # every interval here is a 95 % one
CUT = 0.25  # the IQM cuts a quarter at each end
TAUS = tuple(i / 20 for i in range(21))  # the profile's thresholds: 0, 0.05, ..., 1
CELLS = 1 << 22  # resampled scores held at once (each 8 bytes, thrice): resamples go in chunks


@dataclass(frozen=True)
class Aggregate:
    """A benchmark run's pooled IQM, mean and median, each with its 95 % stratified
    bootstrap interval as (low, high)."""

    iqm: float
    iqm_interval: tuple[float, float]
    mean: float
    mean_interval: tuple[float, float]
    median: float
    median_interval: tuple[float, float]


@dataclass(frozen=True)
class Improvement:
    """The probability that A's episode beats B's on the same task, averaged over tasks,
    with its 95 % stratified bootstrap interval as (low, high)."""

    probability: float
    interval: tuple[float, float]


def iqm(scores: Sequence[float]) -> float:
    """The interquartile mean of ``scores``: the mean of the sorted scores left after
    cutting ``int(0.25 * n)`` from each end (``scipy.stats.trim_mean(scores, 0.25)``).
    Any finite scores: only a benchmark run's must be normalized."""
    if not scores:
        raise ValueError("the interquartile mean of no scores is undefined")
    for i, score in enumerate(scores):
        if not math.isfinite(score):
            raise ValueError(f"scores: score {i} is {score!r}: the IQM needs finite scores")
    ordered = sorted(scores)
    cut = int(CUT * len(ordered))
    middle = ordered[cut : len(ordered) - cut]
    return math.fsum(middle) / len(middle)


def aggregate(
    per_task: Sequence[Sequence[float]], *, resamples: int = RESAMPLES, seed: int = 0
) -> Aggregate:
    """The IQM, mean and median of every episode's score in ``per_task`` (one list of
    normalized scores per task) pooled, with 95 % intervals from ``resamples`` stratified
    bootstrap resamples drawn by a generator seeded with ``seed``."""
    _check(per_task, "per_task")
    _check_resamples(resamples)
    import numpy as np  # noqa: PLC0415 (slow to load: only where a bootstrap runs)

    pooled = np.concatenate([np.asarray(task, dtype=np.float64) for task in per_task])
    sizes = np.array([len(task) for task in per_task], dtype=np.int64)
    starts = np.repeat(np.cumsum(sizes) - sizes, sizes)  # each column's task's first episode
    bounds = np.repeat(sizes, sizes)  # each column's task's number of episodes
    rng = np.random.default_rng(seed)
    chunk = max(1, CELLS // len(pooled))
    parts: list[Array] = []
    for done in range(0, resamples, chunk):
        size = min(chunk, resamples - done)
        picks = starts + rng.integers(0, bounds, size=(size, len(pooled)))
        parts.append(_statistics(np.sort(pooled[picks], axis=1)))
    drawn = np.concatenate(parts, axis=1)  # rows: iqm, mean, median; a column per resample
    low, high = np.quantile(drawn, [(1 - LEVEL) / 2, (1 + LEVEL) / 2], axis=1)
    point = _statistics(np.sort(pooled)[None, :])[:, 0]
    intervals = [(float(lo), float(hi)) for lo, hi in zip(low, high, strict=True)]
    return Aggregate(
        iqm=float(point[0]),
        iqm_interval=intervals[0],
        mean=float(point[1]),
        mean_interval=intervals[1],
        median=float(point[2]),
        median_interval=intervals[2],
    )


def profile(
    per_task: Sequence[Sequence[float]], taus: Sequence[float] | None = None
) -> list[tuple[float, float]]:
    """The performance profile of ``per_task``: for each threshold τ of ``taus`` (by
    default 0 to 1 in steps of 0.05), (τ, the fraction of all episodes scoring above τ)."""
    _check(per_task, "per_task")
    pooled = [score for task in per_task for score in task]
    return [
        (float(tau), sum(score > tau for score in pooled) / len(pooled))
        for tau in (TAUS if taus is None else taus)
    ]


def probability_of_improvement(
    a_per_task: Sequence[Sequence[float]],
    b_per_task: Sequence[Sequence[float]],
    *,
    resamples: int = RESAMPLES,
    seed: int = 0,
) -> Improvement:
    """The probability that an episode of A scores above an episode of B on the same
    task (ties half), averaged over the tasks, which A and B list in the same order; with
    its 95 % interval from ``resamples`` stratified bootstrap resamples of each task's
    episodes of A and of B, drawn by a generator seeded with ``seed``."""
    _check(a_per_task, "a_per_task")
    _check(b_per_task, "b_per_task")
    if len(a_per_task) != len(b_per_task):
        raise ValueError(
            f"A has {len(a_per_task)} tasks and B {len(b_per_task)}: the probability of "
            "improvement compares the same tasks, in the same order"
        )
    _check_resamples(resamples)
    import numpy as np  # noqa: PLC0415 (slow to load: only where a bootstrap runs)

    rng = np.random.default_rng(seed)
    point = 0.0
    drawn = np.zeros(resamples)
    for a_task, b_task in zip(a_per_task, b_per_task, strict=True):
        a = np.asarray(a_task, dtype=np.float64)
        b = np.asarray(b_task, dtype=np.float64)
        # beats[i, j]: how much A's episode i beats B's episode j (1, a tie 1/2, or 0).
        # A resample drawing episode i of A w_i times and j of B v_j times has the
        # probability w · beats · v / (n m): the pairs of the resample, without forming them.
        beats = (a[:, None] > b[None, :]) + 0.5 * (a[:, None] == b[None, :])
        pairs = len(a) * len(b)
        point += float(beats.sum()) / pairs
        w = _counts(rng.integers(0, len(a), size=(resamples, len(a))), len(a))
        v = _counts(rng.integers(0, len(b), size=(resamples, len(b))), len(b))
        drawn += ((w @ beats) * v).sum(axis=1) / pairs
    tasks = len(a_per_task)
    low, high = np.quantile(drawn / tasks, [(1 - LEVEL) / 2, (1 + LEVEL) / 2])
    return Improvement(point / tasks, (float(low), float(high)))


def _statistics(ordered: Array) -> Array:
    """The IQM, mean and median (rows) of each row of ``ordered`` (sorted rows)."""
    import numpy as np  # noqa: PLC0415

    n = ordered.shape[1]
    cut = int(CUT * n)
    half = n // 2
    median = ordered[:, half] if n % 2 else (ordered[:, half - 1] + ordered[:, half]) / 2
    return np.stack([ordered[:, cut : n - cut].mean(axis=1), ordered.mean(axis=1), median])


def _counts(picks: NDArray[np.int64], n: int) -> Array:
    """How many times each of ``n`` episodes was drawn in each row of ``picks``."""
    import numpy as np  # noqa: PLC0415

    rows = np.arange(len(picks))[:, None] * n
    counts = np.bincount((rows + picks).ravel(), minlength=len(picks) * n)
    return counts.reshape(len(picks), n).astype(np.float64)


def _check(per_task: Sequence[Sequence[float]], name: str) -> None:
    """Refuse ``per_task`` unless it has tasks, each with episodes, each a normalized
    score: finite and in [0, 1]."""
    if not per_task:
        raise ValueError(f"{name} has no tasks")
    for t, task in enumerate(per_task):
        if not task:
            raise ValueError(f"{name}: task {t} has no episodes")
        _check_scores(task, f"{name}: task {t}, episode")


def _check_scores(scores: Sequence[float], where: str) -> None:
    for e, score in enumerate(scores):
        if not (math.isfinite(score) and 0.0 <= score <= 1.0):
            raise ValueError(
                f"{where} {e}: {score!r} is not a normalized score (a finite number in [0, 1])"
            )


def _check_resamples(resamples: int) -> None:
    if resamples < 1:
        raise ValueError(f"the bootstrap needs at least one resample, not {resamples}")
