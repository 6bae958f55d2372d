"""The statistics of an evaluation: how sure a score is, and whether one beats another.

An evaluation scores a controller on a fixed suite of episodes, so its numbers are
estimates from a sample of episodes, each with its 95 % interval:

- the success rate with Wilson's score interval (sound at 0 % and 100 % and for few
  episodes, where the normal approximation's interval leaves [0, 1] or has no width);
- the mean reward with a percentile bootstrap interval over episodes, from a seeded
  generator, so the same episodes always give the same interval; or none
  (``mean_interval``) where a bootstrap cannot be a 95 % interval: under
  ``MIN_BOOTSTRAP`` episodes, or rewards all alike.

Two evaluations of the same suite are paired by episode (the same seed, so the same
maze or table). Whether A succeeds more often than B is McNemar's exact test: only the
episodes where exactly one succeeded count, and under "neither is better" each of those
is a fair coin. The paired reward difference has a bootstrap interval like the mean.

Only the bootstrap needs numpy, and imports it when it runs: a client that reads
evaluations (``repository.evaluation``'s models, the ``labd`` command) loads none of it.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass

Z95 = 1.959963984540054  # the standard normal's 97.5th percentile
RESAMPLES = 2000  # bootstrap resamples: the interval's ends move by well under 1 % of its width
LEVEL = 0.95  # every interval here is a 95 % one


def range_coverage(n: int) -> float:
    """The chance that ``n`` independent draws of a continuous distribution straddle its
    median: each falls below it with probability 1/2, so 1 - P(all below) - P(all above)
    = 1 - 2 (1/2)^n."""
    return 1 - 2 * 0.5**n


# The fewest values whose percentile bootstrap interval can be a 95 % one (6). Every
# resample's mean lies within the values' range, so the interval does too, and the range
# holds the median only with probability range_coverage(n): 93.75 % for 5 values, 96.9 %
# for 6. The median is the mean of a symmetric distribution, the most favourable case:
# below 6 values no percentile interval covers the mean 95 % of the time (2 values: half).
MIN_BOOTSTRAP = next(n for n in itertools.count(1) if range_coverage(n) >= LEVEL)


@dataclass(frozen=True)
class Interval:
    """A two-sided 95 % interval."""

    low: float
    high: float

    def overlaps(self, other: Interval) -> bool:
        return self.low <= other.high and other.low <= self.high


def wilson(successes: int, episodes: int, z: float = Z95) -> Interval:
    """Wilson's score interval for ``successes`` in ``episodes``; [0, 1] for none."""
    if not 0 <= successes <= episodes:
        raise ValueError(f"{successes} successes in {episodes} episodes")
    if episodes == 0:
        return Interval(0.0, 1.0)
    p = successes / episodes
    z2 = z * z
    centre = (p + z2 / (2 * episodes)) / (1 + z2 / episodes)
    half = z * math.sqrt(p * (1 - p) / episodes + z2 / (4 * episodes**2)) / (1 + z2 / episodes)
    # at 0 and at every success the exact end is the rate itself: no rounding below or above it
    low = 0.0 if successes == 0 else max(0.0, centre - half)
    high = 1.0 if successes == episodes else min(1.0, centre + half)
    return Interval(low, high)


def bootstrap_mean(
    values: Sequence[float], *, seed: int = 0, resamples: int = RESAMPLES
) -> Interval | None:
    """A percentile bootstrap 95 % interval of the mean of ``values`` (resampled with a
    generator seeded with ``seed``, all at once: a list of evaluations computes one for
    each); None without values."""
    if not values:
        return None
    if len(values) == 1:
        return Interval(values[0], values[0])
    import numpy as np  # noqa: PLC0415 (slow to load: only where a bootstrap runs)

    data = np.asarray(values, dtype=float)
    picks = np.random.default_rng(seed).integers(0, len(data), size=(resamples, len(data)))
    low, high = np.quantile(data[picks].mean(axis=1), [0.025, 0.975])
    return Interval(float(low), float(high))


def mean_interval(
    values: Sequence[float], *, seed: int = 0, resamples: int = RESAMPLES
) -> Interval | None:
    """The 95 % interval of the mean of ``values``, the percentile bootstrap
    (``bootstrap_mean``), where there is one; None for fewer than ``MIN_BOOTSTRAP``
    values (it cannot be a 95 % interval) or values all alike (every resample is the
    same: a zero-width interval would claim a certainty no sample gives; twenty
    episodes of reward 0 say little of a rare one that earns 1000)."""
    if len(values) < MIN_BOOTSTRAP or min(values) == max(values):
        return None
    return bootstrap_mean(values, seed=seed, resamples=resamples)


def paired_difference(
    a: Sequence[float], b: Sequence[float], *, seed: int = 0, resamples: int = RESAMPLES
) -> tuple[float, Interval | None] | None:
    """The mean of ``a[i] - b[i]`` over pairs, with its 95 % interval where there is one
    (``mean_interval``: none over fewer than ``MIN_BOOTSTRAP`` pairs, or differences all
    alike); None without pairs."""
    if len(a) != len(b):
        raise ValueError(f"{len(a)} values paired with {len(b)}")
    differences = [x - y for x, y in zip(a, b, strict=True)]
    if not differences:
        return None
    interval = mean_interval(differences, seed=seed, resamples=resamples)
    return sum(differences) / len(differences), interval


def mcnemar_exact(only_a: int, only_b: int) -> float:
    """McNemar's exact two-sided p-value: the chance, were A and B equally good, of a
    split of the discordant pairs at least as uneven as ``only_a`` to ``only_b``
    (1.0 when there are none)."""
    if only_a < 0 or only_b < 0:
        raise ValueError(f"discordant pairs cannot be negative: {only_a}, {only_b}")
    n = only_a + only_b
    if n == 0:
        return 1.0
    k = min(only_a, only_b)
    # P(X <= k) for X ~ Binomial(n, 1/2), doubled; exact in integers until the division
    tail = sum(math.comb(n, i) for i in range(k + 1))
    return min(1.0, 2 * tail / (1 << n))
