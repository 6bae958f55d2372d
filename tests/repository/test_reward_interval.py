"""An evaluation's reward interval: a 95 % percentile bootstrap where there can be one,
and none where it would be degenerate (too few episodes, every reward the same)."""

from __future__ import annotations

import numpy as np
import pytest

from repository.evaluation import EpisodeRow, score
from repository.stats import bootstrap_mean, wilson
from repository.trial import Outcome, Status


def rows(rewards: list[float], outcome: Outcome = Outcome.SUCCESS) -> list[EpisodeRow]:
    return [
        EpisodeRow(
            episode=i,
            trial=100 + i,
            seed=i,
            status=Status.FINISHED,
            outcome=outcome,
            reward=reward,
            data_digest=f"{i:064x}",
            verified=True,
        )
        for i, reward in enumerate(rewards)
    ]


@pytest.mark.parametrize(
    "rewards",
    [[17.88], [17.88, 18.0], [1.0, 2.0, 3.0, 4.0, 5.0], [0.0] * 20, [999.5] * 6],
    ids=["one", "two", "five", "twenty-zeros", "six-alike"],
)
def test_too_few_or_alike_rewards_have_no_interval_but_a_mean(rewards: list[float]) -> None:
    """One to five episodes, or rewards all the same, give the mean and no interval
    (the issue's one episode read "[17.88, 17.88]"); the success rate keeps Wilson's
    interval, which is wide and valid for any number of episodes."""
    s = score(rows(rewards), seed=3)
    assert s.mean_reward == pytest.approx(sum(rewards) / len(rewards))
    assert s.reward_interval is None
    assert s.success_interval == (wilson(len(rewards), len(rewards)).low, 1.0)


def test_one_episode_has_wilsons_wide_interval_and_no_reward_interval() -> None:
    """One success in one episode: 21 % to 100 % (1 / (1 + z^2) to 1), a valid 95 %
    interval that says how little one episode tells; the reward: a mean alone."""
    s = score(rows([17.88]), seed=1)
    z2 = 1.959963984540054**2
    assert s.success_interval == pytest.approx((1 / (1 + z2), 1.0), abs=1e-12)
    assert (s.mean_reward, s.reward_interval) == (17.88, None)


def test_six_varied_rewards_have_the_percentile_bootstrap_recomputed() -> None:
    """From six episodes with rewards that differ, the interval is the percentile
    bootstrap of their mean, seeded with the evaluation's seed: recomputed here."""
    rewards = [12.5, 17.88, 9.0, 14.25, 20.0, 11.0]
    s = score(rows(rewards), seed=3)
    expected = bootstrap_mean(rewards, seed=3)
    assert expected is not None
    assert s.reward_interval == (expected.low, expected.high)
    # the formula itself: 2000 resamples, their means' 2.5th and 97.5th percentiles
    picks = np.random.default_rng(3).integers(0, 6, size=(2000, 6))
    low, high = np.quantile(np.array(rewards)[picks].mean(axis=1), [0.025, 0.975])
    assert s.reward_interval == (float(low), float(high))
