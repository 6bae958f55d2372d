"""A benchmark run's statistics, held to their definitions (rliable, Agarwal et al. 2021)
recomputed with NumPy and SciPy: the IQM is SciPy's trimmed mean, the bootstrap is
stratified by task and seeded, the profile counts scores above each threshold, and the
probability of improvement is the Mann-Whitney U over n · m averaged over tasks."""

from __future__ import annotations

import math
import random

import numpy as np
import pytest
from scipy import stats as scipy_stats

from repository.benchmark_stats import (
    TAUS,
    Aggregate,
    Improvement,
    aggregate,
    iqm,
    probability_of_improvement,
    profile,
)


def run(seed: int, tasks: int = 5, episodes: int = 12, power: float = 1.0) -> list[list[float]]:
    """A benchmark run of random normalized scores, skewed up for powers below 1."""
    rng = random.Random(seed)
    return [[rng.random() ** power for _ in range(episodes)] for _ in range(tasks)]


def pooled(per_task: list[list[float]]) -> list[float]:
    return [score for task in per_task for score in task]


def test_iqm_is_scipys_trimmed_mean_at_a_quarter() -> None:
    """The IQM cuts int(n / 4) from each end, as scipy.stats.trim_mean(x, 0.25) does."""
    rng = random.Random(37)
    for n in range(1, 51):
        for _ in range(20):
            # some ties too: rounded scores repeat
            scores = [round(rng.random(), rng.choice([1, 2, 17])) for _ in range(n)]
            assert iqm(scores) == pytest.approx(scipy_stats.trim_mean(scores, 0.25), abs=1e-12)


@pytest.mark.parametrize(
    ("scores", "expected"),
    [
        ([0.0, 0.1, 0.2, 0.3], 0.15),  # one cut at each end
        ([0.3, 0.0, 0.2, 0.1], 0.15),  # sorted first
        ([0.7], 0.7),
        ([0.2, 0.4, 0.6], 0.4),  # int(0.75) = 0: nothing cut
        ([0.0, 0.0, 0.5, 0.6, 1.0, 1.0, 1.0, 1.0], 0.775),  # two cut at each end
        ([0.0, 1.0, 0.4, 0.4, 0.5], 1.3 / 3),  # int(1.25) = 1: the middle three
        ([0.0, 1.0, 2.0, 3.0], 1.5),  # any finite scores, not only normalized ones
    ],
)
def test_iqm_by_hand(scores: list[float], expected: float) -> None:
    assert iqm(scores) == pytest.approx(expected, abs=1e-15)


def test_aggregate_points_are_the_pooled_statistics() -> None:
    """The point estimates are the IQM, mean and median of every episode pooled."""
    data = [*run(1, tasks=7, episodes=9), [0.05, 0.99]]  # unequal tasks: pooling, not per task
    result = aggregate(data, resamples=500)
    everything = np.array(pooled(data))
    assert result.iqm == pytest.approx(scipy_stats.trim_mean(everything, 0.25), abs=1e-12)
    assert result.mean == pytest.approx(float(np.mean(everything)), abs=1e-12)
    assert result.median == pytest.approx(float(np.median(everything)), abs=1e-12)


@pytest.mark.parametrize("seed", range(5))
def test_aggregate_intervals_hold_their_points(seed: int) -> None:
    """Every point estimate lies inside its 95 % interval, which has width and lies in [0, 1]."""
    result = aggregate(run(seed, tasks=6, episodes=15), seed=seed)
    for point, (low, high) in [
        (result.iqm, result.iqm_interval),
        (result.mean, result.mean_interval),
        (result.median, result.median_interval),
    ]:
        assert 0.0 <= low < point < high <= 1.0


def test_aggregate_is_reproducible_by_its_seed() -> None:
    """The same scores and seed give the same intervals; another seed, slightly other ones."""
    data = run(2)
    first = aggregate(data, seed=4)
    assert aggregate(data, seed=4) == first
    other = aggregate(data, seed=5)
    assert (other.iqm, other.mean, other.median) == (first.iqm, first.mean, first.median)
    assert other.iqm_interval != first.iqm_interval
    assert other.mean_interval != first.mean_interval
    assert other.iqm_interval == pytest.approx(first.iqm_interval, abs=0.05)
    assert other.mean_interval == pytest.approx(first.mean_interval, abs=0.05)


def test_one_task_is_a_plain_bootstrap_of_its_episodes() -> None:
    """With one task the stratified bootstrap is the plain one: the same generator draws
    the same resamples, so the intervals are the plain bootstrap's percentiles."""
    task = run(3, tasks=1, episodes=17)[0]
    result = aggregate([task], resamples=300, seed=9)
    data = np.array(task)
    picks = np.random.default_rng(9).integers(0, len(task), size=(300, len(task)))
    resampled = data[picks]
    iqms = scipy_stats.trim_mean(resampled, 0.25, axis=1)
    for statistic, interval in [
        (iqms, result.iqm_interval),
        (resampled.mean(axis=1), result.mean_interval),
        (np.median(resampled, axis=1), result.median_interval),
    ]:
        expected = np.quantile(statistic, [0.025, 0.975])
        assert interval == pytest.approx(tuple(expected), abs=1e-12)


def test_a_constant_run_has_degenerate_intervals() -> None:
    result = aggregate([[0.4] * 5, [0.4] * 3])
    assert result == Aggregate(0.4, (0.4, 0.4), 0.4, (0.4, 0.4), 0.4, (0.4, 0.4))


def test_the_bootstrap_keeps_every_tasks_episode_count() -> None:
    """One task of a single 0 and one of a hundred 1s: every stratified resample keeps one
    0 and a hundred 1s, so its mean is exactly 100/101 (a plain bootstrap over the 101
    pooled episodes would draw the 0 anywhere from none to several times)."""
    result = aggregate([[0.0], [1.0] * 100], resamples=2000, seed=1)
    assert result.mean == result.mean_interval[0] == result.mean_interval[1] == 100 / 101
    assert result.iqm_interval == (1.0, 1.0)
    # the check has teeth: the plain bootstrap of the same pool moves the mean
    plain = aggregate([[0.0] + [1.0] * 100], resamples=2000, seed=1)
    assert plain.mean_interval[0] < 100 / 101 <= plain.mean_interval[1]


def test_aggregate_of_the_benchmark_size() -> None:
    """26 tasks of 20 episodes, 2000 resamples: the intervals come out, in [0, 1]."""
    result = aggregate(run(4, tasks=26, episodes=20))
    assert 0.0 < result.iqm_interval[0] < result.iqm < result.iqm_interval[1] < 1.0


def test_profile_by_hand() -> None:
    """The fraction of all episodes strictly above each threshold."""
    data = [[0.0, 0.5, 1.0], [0.2]]
    assert profile(data, [0.0, 0.2, 0.3, 0.5, 0.99, 1.0]) == [
        (0.0, 0.75),  # 0 is not above 0
        (0.2, 0.5),  # nor 0.2 above 0.2
        (0.3, 0.5),
        (0.5, 0.25),
        (0.99, 0.25),
        (1.0, 0.0),  # nothing is above 1
    ]


def test_profile_defaults_to_twenty_one_thresholds_and_never_rises() -> None:
    data = run(5, tasks=4, episodes=30)
    curve = profile(data)
    assert [tau for tau, _ in curve] == list(TAUS) == [i * 5 / 100 for i in range(21)]
    everything = np.array(pooled(data))
    for tau, fraction in curve:
        assert fraction == pytest.approx(float(np.mean(everything > tau)), abs=1e-15)
    fractions = [fraction for _, fraction in curve]
    assert fractions == sorted(fractions, reverse=True)
    assert fractions[0] == 1.0 and fractions[-1] == 0.0


@pytest.mark.parametrize("seed", range(4))
def test_improvement_is_the_mann_whitney_u_over_pairs_averaged_over_tasks(seed: int) -> None:
    """SciPy's U of the first sample counts its wins over the second, ties half; the
    probability of improvement is U / (n m) per task, averaged over tasks."""
    rng = random.Random(seed)
    a = [[round(rng.random(), 1) for _ in range(rng.randint(1, 15))] for _ in range(6)]
    b = [[round(rng.random(), 1) for _ in range(rng.randint(1, 15))] for _ in range(6)]
    expected = sum(
        scipy_stats.mannwhitneyu(x, y).statistic / (len(x) * len(y))
        for x, y in zip(a, b, strict=True)
    ) / len(a)
    assert probability_of_improvement(a, b, resamples=200).probability == pytest.approx(
        expected, abs=1e-12
    )


def test_improvement_by_hand() -> None:
    """A dominates: 1; identical scores: every pair against itself ties, 1/2; mirror: 1 - p."""
    assert probability_of_improvement([[0.9, 1.0]], [[0.1, 0.2, 0.8]]) == Improvement(
        1.0, (1.0, 1.0)
    )
    same = run(6, tasks=3, episodes=8)
    half = probability_of_improvement(same, same)
    assert half.probability == 0.5
    a, b = run(7, power=0.7), run(8)
    forward = probability_of_improvement(a, b).probability
    assert probability_of_improvement(b, a).probability == pytest.approx(1 - forward, abs=1e-12)
    # one pair per task: A wins the first, ties the second, loses the third
    assert (
        probability_of_improvement([[0.6], [0.5], [0.1]], [[0.5], [0.5], [0.2]]).probability == 0.5
    )


@pytest.mark.parametrize("seed", range(4))
def test_improvement_interval_holds_its_point_and_its_seed(seed: int) -> None:
    a, b = run(seed, tasks=8, power=0.8), run(100 + seed, tasks=8)
    result = probability_of_improvement(a, b, seed=seed)
    low, high = result.interval
    assert 0.0 <= low < result.probability < high <= 1.0
    assert probability_of_improvement(a, b, seed=seed) == result
    assert probability_of_improvement(a, b, seed=seed + 1).interval != result.interval


def test_improvement_interval_is_the_stratified_bootstrap() -> None:
    """Each resample draws each task's A and B episodes independently, with replacement,
    and recomputes U / (n m) on them: done here pair by pair for a few resamples."""
    a, b = run(9, tasks=3, episodes=6), run(10, tasks=3, episodes=4)
    resamples = 50
    rng = np.random.default_rng(3)
    per_resample = np.zeros(resamples)
    for x, y in zip(a, b, strict=True):
        xs = np.array(x)[rng.integers(0, len(x), size=(resamples, len(x)))]
        ys = np.array(y)[rng.integers(0, len(y), size=(resamples, len(y)))]
        for r in range(resamples):
            per_resample[r] += scipy_stats.mannwhitneyu(xs[r], ys[r]).statistic / (len(x) * len(y))
    expected = np.quantile(per_resample / len(a), [0.025, 0.975])
    got = probability_of_improvement(a, b, resamples=resamples, seed=3).interval
    assert got == pytest.approx(tuple(expected), abs=1e-12)


def test_improvement_refuses_tasks_that_do_not_match() -> None:
    with pytest.raises(ValueError, match="A has 2 tasks and B 3"):
        probability_of_improvement(run(1, tasks=2), run(2, tasks=3))
    with pytest.raises(ValueError, match="b_per_task: task 1 has no episodes"):
        probability_of_improvement([[0.5], [0.5]], [[0.5], []])
    with pytest.raises(ValueError, match="a_per_task: task 0 has no episodes"):
        probability_of_improvement([[]], [[0.5]])


@pytest.mark.parametrize(
    ("per_task", "message"),
    [
        ([], "per_task has no tasks"),
        ([[0.5], []], "task 1 has no episodes"),
        ([[0.5, math.nan]], "task 0, episode 1: nan is not a normalized score"),
        ([[0.5], [math.inf]], "task 1, episode 0: inf is not"),
        ([[1.5]], "1.5 is not a normalized score"),
        ([[0.2, -0.01]], "-0.01 is not a normalized score"),
    ],
)
def test_nonsense_is_refused(per_task: list[list[float]], message: str) -> None:
    """Empty runs, empty tasks and scores that are not finite or not in [0, 1] are errors
    that say which task and episode."""
    with pytest.raises(ValueError, match=message):
        aggregate(per_task)
    with pytest.raises(ValueError, match=message):
        profile(per_task)


def test_iqm_and_the_bootstrap_refuse_nonsense() -> None:
    with pytest.raises(ValueError, match="no scores"):
        iqm([])
    with pytest.raises(ValueError, match="score 1 is nan: the IQM needs finite scores"):
        iqm([0.5, math.nan])
    with pytest.raises(ValueError, match="at least one resample"):
        aggregate([[0.5]], resamples=0)
    with pytest.raises(ValueError, match="at least one resample"):
        probability_of_improvement([[0.5]], [[0.5]], resamples=0)
