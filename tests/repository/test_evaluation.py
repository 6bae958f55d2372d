"""The evaluation record's logic: suites and their seeds, a score from its episodes, two
evaluations paired by episode, and the leaderboard of evaluations."""

from __future__ import annotations

import datetime as dt

import pytest

from repository.evaluation import (
    CANCELLED,
    LAB_BROKE,
    EpisodeRow,
    Evaluation,
    Suite,
    compare,
    episodes_sha256,
    held_out_seeds,
    hide,
    leaderboard,
    partiality,
    score,
    statement,
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


def row(episode: int, outcome: Outcome | None, reward: float | None = None, *, status: Status = Status.FINISHED, verified: bool | None = True, lab_fault: bool = False) -> EpisodeRow:  # fmt: skip
    return EpisodeRow(
        episode=episode,
        trial=100 + episode,
        seed=episode,
        status=status,
        outcome=outcome,
        reward=reward,
        verified=verified,
        compute_seconds=2.0,
        data_digest=f"{episode:064x}" if status is Status.FINISHED else None,
        lab_fault=lab_fault,
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


def test_an_evaluation_runs_until_every_episode_ended_and_counts_every_episode() -> None:
    """Its rate is over the suite's episodes, known once all have ended: a cancelled
    episode is no success, and makes the evaluation partial even when only it was."""
    queued = [row(i, None, status=Status.QUEUED) for i in range(3)]
    assert status_of(queued, cancel_requested=False) is Status.QUEUED
    started = [row(0, Outcome.SUCCESS), *queued[1:]]
    assert status_of(started, cancel_requested=False) is Status.RUNNING
    assert score(started, seed=0).success_rate is None  # not over yet
    assert partiality(started, cancel_requested=False) is None
    cancelled = [row(0, Outcome.SUCCESS), *(row(i, None, status=Status.CANCELLED) for i in (1, 2))]
    assert status_of(cancelled, cancel_requested=True) is Status.CANCELLED
    s = score(cancelled, seed=0)
    assert (s.done, s.successes, s.success_rate) == (1, 1, pytest.approx(1 / 3))
    assert s.success_interval is not None and s.success_interval[1] < 1.0
    # the per-episode cancel: the evaluation itself was never cancelled, yet it is partial
    assert status_of(cancelled, cancel_requested=False) is Status.CANCELLED
    assert partiality(cancelled, cancel_requested=False) == (
        CANCELLED,
        "2 episodes cancelled (episodes 1, 2)",
    )
    every = [row(i, Outcome.ERROR) for i in range(3)]  # a repository that errors on each
    assert status_of(every, cancel_requested=False) is Status.FINISHED
    assert score(every, seed=0).success_rate == 0.0
    assert partiality(every, cancel_requested=False) is None  # the controller's errors count
    broken = [row(0, Outcome.SUCCESS), row(1, Outcome.ERROR, lab_fault=True), row(2, Outcome.FAIL)]
    assert partiality(broken, cancel_requested=False) == (
        LAB_BROKE,
        "the lab broke 1 episode (episode 1), not the controller",
    )


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
        "status": status_of(rows, cancel_requested=False),
        "partial": False,
        "created": dt.datetime(2026, 11, 1, tzinfo=dt.UTC),
        "finished": None,
        **dict(score(rows, seed=eid)),
        "rows": rows,
    }
    found = partiality(rows, cancel_requested=False)
    if found is not None:
        values.update(partial=True, partial_cause=found[0], partial_reason=found[1])
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


def test_the_leaderboard_ranks_each_commits_first_evaluation_never_its_best() -> None:
    first = evaluation(1, "a" * 40, [S] * 6 + [F] * 4)
    luckier = evaluation(2, "a" * 40, [S] * 9 + [F])  # the same commit again: never its row
    close = evaluation(3, "b" * 40, [S] * 8 + [F] * 2)
    far = evaluation(4, "c" * 40, [F] * 10)
    running = evaluation(6, "e" * 40, [S] * 10, status=Status.RUNNING)
    rows = leaderboard([luckier, far, close, first, running])
    assert [(r.rank, r.evaluation) for r in rows] == [(1, 3), (2, 1), (3, 4)]
    assert [r.tie for r in rows] == [False, True, False]  # 8/10 and 6/10 overlap; 0/10 does not
    assert rows[0].success_interval[0] < 0.8 < rows[0].success_interval[1]


def test_cancelling_buys_nothing_on_the_leaderboard() -> None:
    """An evaluation with an episode cancelled is partial, off the board; a commit whose
    first evaluation was cancelled gets no row from a later one."""
    cancelled = [Status.CANCELLED] * 8
    gamed = evaluation(
        1, "a" * 40, [S, S],
        rows=[row(0, S), row(1, S), *(row(i, None, status=st) for i, st in enumerate(cancelled, 2))],
    )  # fmt: skip
    gamed = gamed.model_copy(update=dict(score(gamed.rows, seed=1)))
    gamed = gamed.model_copy(
        update={"status": Status.CANCELLED, "partial": True, "partial_cause": CANCELLED}
    )
    retried = evaluation(2, "a" * 40, [S] * 10)  # the same commit, submitted again
    honest = evaluation(3, "b" * 40, [S] * 3 + [F] * 7)
    rows = leaderboard([gamed, retried, honest])
    assert [(r.rank, r.evaluation) for r in rows] == [(1, 3)]


def test_a_commit_whose_first_evaluation_the_lab_broke_is_ranked_by_its_next() -> None:
    broken = evaluation(
        1, "a" * 40, [S, F], rows=[row(0, S), row(1, Outcome.ERROR, lab_fault=True)]
    )
    broken = broken.model_copy(update={"partial": True, "partial_cause": LAB_BROKE})
    next_one = evaluation(2, "a" * 40, [S, F])
    assert [(r.rank, r.evaluation) for r in leaderboard([broken, next_one])] == [(1, 2)]


def test_rows_not_verified_by_the_lab_are_listed_apart_unranked() -> None:
    ranked = evaluation(1, "a" * 40, [S] + [F] * 9)
    unverified = evaluation(2, "b" * 40, [S] * 10, verified=False)
    rows = leaderboard([unverified, ranked])
    assert [(r.rank, r.evaluation, r.verified) for r in rows] == [(1, 1, True), (None, 2, False)]
    assert rows[1].note is not None and rows[1].note.startswith("not ranked")
    assert not rows[1].tie


def test_a_rerun_never_replaces_a_row_and_a_diverged_one_marks_it() -> None:
    original = evaluation(1, "a" * 40, [S] * 5 + [F] * 5)
    lucky_rerun = evaluation(
        2, "a" * 40, [S] * 10, rerun_of=1, submitter="mallory",
        reproduced="diverged: 5 of 10 episodes identical; episodes 5, 6, 7, 8, 9 differ",
    )  # fmt: skip
    rows = leaderboard([original, lucky_rerun])
    assert [(r.evaluation, r.submitter, r.success_rate) for r in rows] == [(1, "alice", 0.5)]
    assert rows[0].reproducible is False and "rerun 2 diverged" in (rows[0].note or "")
    same = evaluation(3, "a" * 40, [S] * 5 + [F] * 5, rerun_of=1, reproduced="reproduced: 10 of 10 episodes identical")  # fmt: skip
    assert leaderboard([original, same])[0].reproducible is True
    assert leaderboard([original])[0].reproducible is None


def test_a_hidden_evaluation_shows_its_aggregate_alone_and_nothing_while_it_runs() -> None:
    done = evaluation(1, "a" * 40, [S, F, S], [1.0, 0.0, 1.0], held_out=True)
    shown = hide(done)
    assert shown.hidden and shown.rows == [] and shown.compute_seconds is None
    assert (shown.success_rate, shown.successes, shown.verified) == (
        pytest.approx(2 / 3),
        2,
        True,
    )
    running = evaluation(2, "a" * 40, [S, F], status=Status.RUNNING, held_out=True)
    seen = hide(running)
    assert (seen.done, seen.running, seen.queued, seen.successes, seen.mean_reward) == (
        None, None, None, None, None,
    )  # fmt: skip
    rerun = hide(
        done.model_copy(
            update={"reproduced": "diverged: 2 of 3 episodes identical; episodes 1 differ"}
        )
    )
    assert rerun.reproduced == "diverged: 2 of 3 episodes identical"


def test_a_held_out_statement_commits_to_its_episodes_without_listing_them() -> None:
    public = evaluation(1, "a" * 40, [S, F])
    said = statement(public, 0.0)
    assert [r["seed"] for r in said["rows"]] == [0, 1] and said["successes"] == 1
    held = evaluation(2, "a" * 40, [S, F], held_out=True)
    said = statement(held, 0.0)
    assert "rows" not in said and "seed" not in str(said)
    assert said["episodes_sha256"] == episodes_sha256(held.rows)
    assert said["episodes_sha256"] != episodes_sha256([held.rows[1], held.rows[0]])
    assert (said["partial"], said["episodes"], said["success_rate"]) == (False, 2, 0.5)
