"""A benchmark's declaration (``repository.benchmark``): names and suites are checked when
it is made, and an episode's normalized score is its return over the scale, clipped to
[0, 1], or its success; a broken episode scores 0."""

from __future__ import annotations

import pytest
from pydantic import ValidationError

from repository.benchmark import (
    Benchmark,
    BenchmarkList,
    BenchmarkTask,
    By,
    Normalize,
    normalized,
)
from repository.evaluation import EpisodeRow
from repository.trial import Outcome, Status

BY_RETURN = Normalize(by=Normalize.RETURN, scale=1000.0)
BY_SUCCESS = Normalize(by=Normalize.SUCCESS)


def episode(outcome: Outcome | None, reward: float | None) -> EpisodeRow:
    status = Status.RUNNING if outcome is None else Status.FINISHED
    return EpisodeRow(episode=0, trial=7, seed=0, status=status, outcome=outcome, reward=reward)


def test_a_benchmark_is_declared_with_its_tasks_suites_and_normalization():
    """A declaration keeps what it was given; a task's suite is dev unless it says."""
    made = Benchmark(
        name="dmc-2",
        doc="two tasks",
        tasks=(
            BenchmarkTask(task="dmc-cartpole-balance", normalize=BY_RETURN),
            BenchmarkTask(task="icreate-maze", suite="test", normalize=BY_SUCCESS),
        ),
    )
    assert [(t.task, t.suite, t.normalize.by) for t in made.tasks] == [
        ("dmc-cartpole-balance", "dev", By.RETURN),
        ("icreate-maze", "test", By.SUCCESS),
    ]
    assert made.task("icreate-maze") is made.tasks[1] and made.task("other") is None
    assert BY_RETURN.describe() == "the return over 1000, clipped to [0, 1]"
    assert BY_SUCCESS.describe() == "1 if the episode succeeded, else 0"


def test_a_benchmark_round_trips_through_json():
    """What the API sends (a list of benchmarks) reads back as the same declarations."""
    made = Benchmark(
        name="one",
        doc="d",
        tasks=(BenchmarkTask(task="dmc-reacher-easy", normalize=BY_RETURN),),
    )
    sent = BenchmarkList([made]).model_dump_json()
    assert BenchmarkList.model_validate_json(sent).root == [made]
    assert BenchmarkList([made]).model_dump(mode="json")[0]["tasks"][0] == {
        "task": "dmc-reacher-easy",
        "suite": "dev",
        "normalize": {"by": "return", "scale": 1000.0},
    }


@pytest.mark.parametrize(
    ("name", "said"),
    [
        ("DMC", "lowercase letters, digits and '-'"),
        ("dmc_classic", "lowercase letters, digits and '-'"),
        ("-dmc", "lowercase letters, digits and '-'"),
        ("", "lowercase letters, digits and '-'"),
        ("x" * 65, "lowercase letters, digits and '-'"),
    ],
)
def test_a_benchmark_name_is_lowercase_letters_digits_and_dashes(name, said):
    """A name other than lowercase letters, digits and '-' (1 to 64) is refused."""
    with pytest.raises(ValidationError, match=said):
        Benchmark(name=name, doc="d", tasks=(BenchmarkTask(task="t", normalize=BY_SUCCESS),))


def test_a_bad_declaration_is_refused_saying_why():
    """No tasks, a task named twice, a malformed task or suite name, an empty doc, a
    return without a positive scale, a scale on success: each is refused."""
    task = BenchmarkTask(task="t", normalize=BY_SUCCESS)
    with pytest.raises(ValidationError, match="at least 1 item"):
        Benchmark(name="b", doc="d", tasks=())
    with pytest.raises(ValidationError, match="names each task once; t more than once"):
        Benchmark(name="b", doc="d", tasks=(task, task))
    with pytest.raises(ValidationError, match="at least 1 character"):
        Benchmark(name="b", doc="", tasks=(task,))
    with pytest.raises(ValidationError, match="'Cart Pole' is not a task's name"):
        BenchmarkTask(task="Cart Pole", normalize=BY_SUCCESS)
    with pytest.raises(ValidationError, match="'Dev' is not a suite's name"):
        BenchmarkTask(task="t", suite="Dev", normalize=BY_SUCCESS)
    for scale in (None, 0.0, -1.0, float("inf"), float("nan")):
        with pytest.raises(ValidationError, match="positive finite scale"):
            Normalize(by=Normalize.RETURN, scale=scale)
    with pytest.raises(ValidationError, match="takes no scale"):
        Normalize(by=Normalize.SUCCESS, scale=1000.0)
    with pytest.raises(ValidationError, match="Extra inputs"):
        BenchmarkTask(task="t", normalize=BY_SUCCESS, suites="dev")  # type: ignore[call-arg]


@pytest.mark.parametrize(
    ("outcome", "reward", "score"),
    [
        (Outcome.SUCCESS, 912.5, 0.9125),
        (Outcome.FAIL, 250.0, 0.25),
        (Outcome.FAIL, 0.0, 0.0),
        (Outcome.SUCCESS, 1000.0, 1.0),
        (Outcome.SUCCESS, 1000.4, 1.0),  # a return past the scale is clipped
        (Outcome.FAIL, -3.0, 0.0),
        (Outcome.ERROR, 600.0, 0.0),  # a broken episode earns nothing
        (Outcome.ERROR, None, 0.0),
    ],
)
def test_a_return_is_normalized_over_its_scale_and_clipped(outcome, reward, score):
    """By return, an episode scores its reward over the scale, clipped to [0, 1]."""
    task = BenchmarkTask(task="dmc-cartpole-balance", normalize=BY_RETURN)
    assert normalized(task, episode(outcome, reward)) == pytest.approx(score, abs=1e-12)


@pytest.mark.parametrize(
    ("outcome", "reward", "score"),
    [
        (Outcome.SUCCESS, None, 1.0),
        (Outcome.SUCCESS, 3.0, 1.0),
        (Outcome.FAIL, 999.0, 0.0),
        (Outcome.ERROR, None, 0.0),
    ],
)
def test_success_scores_one_and_anything_else_zero(outcome, reward, score):
    """By success, an episode scores 1 if it succeeded, whatever its reward, else 0."""
    task = BenchmarkTask(task="icreate-maze", normalize=BY_SUCCESS)
    assert normalized(task, episode(outcome, reward)) == score


def test_an_episode_without_a_score_is_refused():
    """An episode not ended, or one ended without a return that is normalized by return,
    is a ValueError, not a silent 0."""
    by_return = BenchmarkTask(task="dmc-cartpole-balance", normalize=BY_RETURN)
    with pytest.raises(ValueError, match="has not ended"):
        normalized(by_return, episode(None, None))
    for reward in (None, float("nan")):
        with pytest.raises(ValueError, match="cannot be normalized by return"):
            normalized(by_return, episode(Outcome.FAIL, reward))
