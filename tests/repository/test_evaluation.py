"""The evaluation record's logic: suites and their seeds, a score from its episodes, two
evaluations paired by episode, and the leaderboard of evaluations."""

from __future__ import annotations

import datetime as dt

import pytest

from repository.evaluation import (
    EpisodeRow,
    Evaluation,
    Suite,
    compare,
    held_out_seeds,
    leaderboard,
    score,
    status_of,
)
from repository.trial import Outcome, Status

SECRET = b"s" * 32


def test_a_public_suite_lists_its_seeds_and_a_held_out_one_derives_them() -> None:
    dev = Suite("dev", 1, seeds=(3, 1, 2))
    assert (dev.episodes, dev.seeds_with(SECRET, "t")) == (3, [3, 1, 2])
    test = Suite("test", 1, episodes=50, held_out=True)
    seeds = test.seeds_with(SECRET, "icreate-maze")
    assert len(set(seeds)) == 50 and all(0 <= s < 2**63 for s in seeds)
    assert seeds == test.seeds_with(SECRET, "icreate-maze")  # the same on every run
    assert seeds != test.seeds_with(b"t" * 32, "icreate-maze")  # another lab's secret
    assert seeds != Suite("test", 2, episodes=50, held_out=True).seeds_with(SECRET, "icreate-maze")
    assert seeds[:5] == held_out_seeds(SECRET, "icreate-maze", "test", 1, 5)


@pytest.mark.parametrize(
    ("kwargs", "error"),
    [
        ({"name": "Dev", "version": 1, "seeds": (1,)}, "lower-case"),
        ({"name": "dev", "version": 0, "seeds": (1,)}, "versions start at 1"),
        ({"name": "dev", "version": 1, "seeds": (1, 1)}, "twice"),
        ({"name": "dev", "version": 1}, "from 1 to"),
        ({"name": "test", "version": 1, "seeds": (1,), "held_out": True}, "secret"),
        ({"name": "dev", "version": 1, "seeds": (-1,)}, "seeds from 0"),
    ],
)
def test_a_suite_that_makes_no_sense_is_refused_when_declared(kwargs, error) -> None:
    with pytest.raises(ValueError, match=error):
        Suite(**kwargs)


def row(episode: int, outcome: Outcome | None, reward: float | None = None, *, status: Status = Status.FINISHED, verified: bool | None = True) -> EpisodeRow:  # fmt: skip
    return EpisodeRow(
        episode=episode,
        trial=100 + episode,
        seed=episode,
        status=status,
        outcome=outcome,
        reward=reward,
        verified=verified,
        compute_seconds=2.0,
    )


def test_a_score_counts_finished_episodes_with_intervals() -> None:
    rows = [row(i, Outcome.SUCCESS, 1.0) for i in range(7)] + [
        row(i, Outcome.FAIL, 0.0) for i in range(7, 10)
    ]
    s = score(rows, seed=1)
    assert (s.episodes, s.done, s.successes, s.success_rate) == (10, 10, 7, 0.7)
    assert s.success_interval == pytest.approx((0.3968, 0.8922), abs=1e-4)  # Wilson, 7 of 10
    assert s.mean_reward == pytest.approx(0.7)
    assert s.reward_interval is not None and s.reward_interval[0] < 0.7 < s.reward_interval[1]
    assert s.verified and s.compute_seconds == 20.0
    unverified = score([*rows[:-1], row(9, Outcome.FAIL, 0.0, verified=None)], seed=1)
    assert not unverified.verified


def test_an_evaluation_runs_until_every_episode_ended_and_cancelled_keeps_what_finished() -> None:
    queued = [row(i, None, status=Status.QUEUED) for i in range(3)]
    assert status_of(queued, cancel_requested=False) is Status.QUEUED
    started = [row(0, Outcome.SUCCESS), *queued[1:]]
    assert status_of(started, cancel_requested=False) is Status.RUNNING
    cancelled = [row(0, Outcome.SUCCESS), *(row(i, None, status=Status.CANCELLED) for i in (1, 2))]
    assert status_of(cancelled, cancel_requested=True) is Status.CANCELLED
    s = score(cancelled, seed=0)
    assert (s.done, s.successes, s.success_rate) == (1, 1, 1.0)
    every = [row(i, Outcome.ERROR) for i in range(3)]  # a repository that errors on each
    assert status_of(every, cancel_requested=False) is Status.FINISHED
    assert score(every, seed=0).success_rate == 0.0


def evaluation(eid: int, commit: str, outcomes: list[Outcome], rewards: list[float] | None = None, **changes) -> Evaluation:  # fmt: skip
    rows = [row(i, o, (rewards or [None] * len(outcomes))[i]) for i, o in enumerate(outcomes)]
    values = {
        "id": eid,
        "task": "icreate-maze",
        "task_version": "1",
        "suite": "dev",
        "suite_version": 1,
        "held_out": False,
        "repository": "https://example.org/r.git",
        "ref": None,
        "commit": commit,
        "params": {},
        "submitter": "alice",
        "rerun_of": None,
        "status": Status.FINISHED,
        "partial": False,
        "created": dt.datetime(2026, 11, 1, tzinfo=dt.UTC),
        "finished": None,
        **dict(score(rows, seed=eid)),
        "rows": rows,
    }
    return Evaluation(**{**values, **changes})


S, F = Outcome.SUCCESS, Outcome.FAIL


def test_two_evaluations_pair_by_episode_and_say_it_in_a_sentence() -> None:
    """A succeeds on 9 episodes where B fails, B on 1 where A fails: p = 0.021."""
    a = evaluation(
        1, "a" * 40, [S] * 9 + [F] + [S] * 5 + [F] * 5, [1.0] * 9 + [0.0] + [1.0] * 5 + [0.0] * 5
    )
    b = evaluation(
        2, "b" * 40, [F] * 9 + [S] + [S] * 5 + [F] * 5, [0.0] * 9 + [1.0] + [1.0] * 5 + [0.0] * 5
    )
    c = compare(a, b)
    assert (c.pairs.both, c.pairs.only_a, c.pairs.only_b, c.pairs.neither) == (5, 9, 1, 5)
    assert c.paired == 20
    assert c.p_value == pytest.approx(0.021484375)
    assert c.reward_difference == pytest.approx(0.4)
    assert (
        "A (1) succeeds on 9 episodes where B (2) fails, B on 1 where A fails: p = 0.021" in c.said
    )
    assert (
        "B (1) succeeds on 9 episodes where A (2) fails, A on 1 where B fails" in compare(b, a).said
    )
    same = compare(a, a)
    assert same.p_value == 1.0 and "nothing tells them apart" in same.said


def test_only_evaluations_of_one_suite_version_compare() -> None:
    a = evaluation(1, "a" * 40, [S])
    with pytest.raises(ValueError, match="only evaluations of one suite"):
        compare(a, evaluation(2, "b" * 40, [S], suite="test"))
    with pytest.raises(ValueError, match="do not pair"):
        compare(a, evaluation(3, "b" * 40, [S], suite_version=2))
    with pytest.raises(ValueError, match="do not pair"):
        compare(a, evaluation(4, "b" * 40, [S], task_version="2"))


def test_the_leaderboard_ranks_each_commits_best_complete_evaluation() -> None:
    best = evaluation(1, "a" * 40, [S] * 9 + [F])
    again = evaluation(2, "a" * 40, [S] * 5 + [F] * 5)  # the same commit, worse: not listed
    close = evaluation(3, "b" * 40, [S] * 8 + [F] * 2)
    far = evaluation(4, "c" * 40, [F] * 10)
    partial = evaluation(5, "d" * 40, [S] * 10, partial=True, status=Status.CANCELLED)
    running = evaluation(6, "e" * 40, [S] * 10, status=Status.RUNNING)
    rows = leaderboard([again, far, partial, close, best, running])
    assert [(r.rank, r.evaluation) for r in rows] == [(1, 1), (2, 3), (3, 4)]
    assert [r.tie for r in rows] == [False, True, False]  # 9/10 and 8/10 overlap; 0/10 does not
    assert rows[0].success_interval[0] < 0.9 < rows[0].success_interval[1]
