"""An evaluation's statistics, held to SciPy's: Wilson's interval, McNemar's exact test,
and bootstrap intervals that are seeded, cover the mean and narrow with more episodes,
and are none where they cannot be 95 % intervals."""

from __future__ import annotations

import random

import pytest
from scipy import stats as scipy_stats

from repository.stats import (
    MIN_BOOTSTRAP,
    Interval,
    bootstrap_mean,
    mcnemar_exact,
    mean_interval,
    paired_difference,
    range_coverage,
    wilson,
)


@pytest.mark.parametrize(
    ("successes", "episodes"), [(0, 1), (1, 1), (0, 20), (20, 20), (7, 20), (14, 20), (1, 50), (33, 50), (500, 1000)]
)  # fmt: skip
def test_wilson_is_scipys_wilson_interval(successes: int, episodes: int) -> None:
    """The success interval is Wilson's score interval, as SciPy computes it."""
    expected = scipy_stats.binomtest(successes, episodes).proportion_ci(method="wilson")
    got = wilson(successes, episodes)
    assert got.low == pytest.approx(expected.low, abs=1e-12)
    assert got.high == pytest.approx(expected.high, abs=1e-12)
    assert 0.0 <= got.low <= successes / episodes <= got.high <= 1.0


def test_wilson_of_no_episodes_is_everything_and_nonsense_is_refused() -> None:
    assert wilson(0, 0) == Interval(0.0, 1.0)
    for successes, episodes in [(3, 2), (-1, 5)]:
        with pytest.raises(ValueError, match="successes"):
            wilson(successes, episodes)


@pytest.mark.parametrize(
    ("only_a", "only_b"), [(9, 1), (1, 9), (0, 6), (5, 5), (3, 0), (12, 30), (0, 1)]
)
def test_mcnemar_is_the_exact_binomial_test_of_the_discordant_pairs(
    only_a: int, only_b: int
) -> None:
    """McNemar's exact p-value is the two-sided binomial test of one split at p = 1/2."""
    expected = scipy_stats.binomtest(only_a, only_a + only_b, 0.5).pvalue
    assert mcnemar_exact(only_a, only_b) == pytest.approx(expected, rel=1e-12)


def test_mcnemar_without_discordant_pairs_finds_no_difference() -> None:
    assert mcnemar_exact(0, 0) == 1.0
    assert mcnemar_exact(9, 1) == pytest.approx(0.021484375)  # 22/1024: "p = 0.02"
    with pytest.raises(ValueError):
        mcnemar_exact(-1, 3)


def test_bootstrap_is_seeded_covers_the_mean_and_narrows_with_more_episodes() -> None:
    """The same rewards and seed give the same interval; it holds the mean; with four
    times the episodes from the same distribution it is about half as wide."""
    rng = random.Random(7)
    few = [rng.gauss(10.0, 2.0) for _ in range(25)]
    many = [rng.gauss(10.0, 2.0) for _ in range(400)]
    once, again = bootstrap_mean(few, seed=3), bootstrap_mean(few, seed=3)
    assert once == again is not None
    assert bootstrap_mean(few, seed=4) != once
    mean = sum(few) / len(few)
    assert once.low < mean < once.high
    wide, narrow = once.high - once.low, _width(bootstrap_mean(many, seed=3))
    assert 0.15 < narrow / wide < 0.4  # 1/4 expected: sqrt(25/400)
    # and about the normal interval's width, 2 * 1.96 * s / sqrt(n)
    s = (sum((x - mean) ** 2 for x in few) / (len(few) - 1)) ** 0.5
    assert wide == pytest.approx(2 * 1.96 * s / len(few) ** 0.5, rel=0.2)


def test_bootstrap_of_nothing_or_one_value() -> None:
    assert bootstrap_mean([]) is None
    assert bootstrap_mean([2.5]) == Interval(2.5, 2.5)


def test_the_fewest_values_for_a_95_percent_bootstrap_is_where_their_range_can_hold_it() -> None:
    """The percentile interval lies within the values' range (every resample's mean
    does), and n draws of a continuous distribution straddle its median with probability
    1 - P(all below) - P(all above) = 1 - 2 Binomial(n, 1/2).pmf(0): below 95 % up to 5
    values (93.75 %), above from 6 (96.9 %). For a symmetric distribution the median is
    the mean, so under 6 values no percentile bootstrap is a 95 % interval of it."""
    for n in range(1, 12):
        expected = 1 - 2 * scipy_stats.binom.pmf(0, n, 0.5)
        assert range_coverage(n) == pytest.approx(expected, abs=1e-15)
    assert MIN_BOOTSTRAP == min(n for n in range(1, 100) if 1 - 2 * 0.5**n >= 0.95) == 6
    # and the bootstrap's own coverage of a normal mean: two values, about one time in two
    rng = random.Random(11)
    covered = 0
    for trial in range(400):
        interval = bootstrap_mean([rng.gauss(0.0, 1.0) for _ in range(2)], seed=trial)
        assert interval is not None
        covered += interval.low <= 0.0 <= interval.high
    assert 0.4 < covered / 400 < 0.6


def test_a_mean_interval_over_too_few_or_alike_values_is_none() -> None:
    """Under MIN_BOOTSTRAP values, or values all alike (a zero-width interval claims a
    certainty no sample gives), the mean has no interval; otherwise it is the percentile
    bootstrap, as bootstrap_mean computes it."""
    values = [17.88, 3.5, 9.25, 12.0, 4.75, 8.5, 1.25]
    for n in range(MIN_BOOTSTRAP):
        assert mean_interval(values[:n], seed=5) is None
    assert bootstrap_mean([17.88], seed=5) == Interval(17.88, 17.88)  # the degenerate one
    assert mean_interval([17.88], seed=5) is None
    assert mean_interval([0.0] * 20, seed=5) is None
    assert mean_interval([1000.0] * 50, seed=5) is None
    enough = values[:MIN_BOOTSTRAP]
    got = mean_interval(enough, seed=5)
    assert got is not None and got == bootstrap_mean(enough, seed=5)
    assert got.low < sum(enough) / len(enough) < got.high
    assert mean_interval([0.0] * 19 + [1.0], seed=5) == bootstrap_mean([0.0] * 19 + [1.0], seed=5)


def test_paired_difference_is_the_mean_difference_with_its_interval() -> None:
    a = [1.0, 2.0, 3.0, 4.0, 5.0, 6.0]
    b = [0.5, 1.5, 2.5, 3.5, 4.5, 5.5]
    mean, interval = paired_difference(a, b, seed=1)
    assert mean == pytest.approx(0.5) and interval is None  # every pair differs by 0.5
    c = [0.5, 1.0, 2.0, 3.5, 4.0, 6.5]  # differences 0.5, 1, 1, 0.5, 1, -0.5
    mean, interval = paired_difference(a, c, seed=1)
    assert mean == pytest.approx(3.5 / 6)
    assert interval == mean_interval([0.5, 1.0, 1.0, 0.5, 1.0, -0.5], seed=1)
    assert interval is not None and interval.low < mean < interval.high
    assert paired_difference(a[:5], c[:5], seed=1) == (pytest.approx(0.8), None)  # 5 pairs
    assert paired_difference([], []) is None
    with pytest.raises(ValueError, match="paired"):
        paired_difference([1.0], [1.0, 2.0])


def _width(interval: Interval | None) -> float:
    assert interval is not None
    return interval.high - interval.low
