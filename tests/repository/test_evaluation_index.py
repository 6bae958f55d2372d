"""The evaluations in the index, on SQLite and PostgreSQL: an evaluation and its episodes
written with their trials, read back with their outcomes and verdicts, found by filter;
a held-out suite's trials kept out of the archive's reads until the suite is retired."""

from __future__ import annotations

import pytest
import sqlalchemy as sa

from repository.errors import HeldOut, RecordNotFound
from repository.evaluation_index import EvaluationFilters, Evaluations
from repository.index import Derived, Filters, Index
from repository.tables import trials as T
from repository.trial import Order, Status
from repository.well_known import REPLAY

COMMIT = "c" * 40


def add(index: Index, evaluations: Evaluations, *, held_out: bool, seeds: list[int]) -> int:
    with index.begin() as db:
        asked = Order(
            repository="https://example.org/r.git",
            ref="main",
            commit=COMMIT,
            task="icreate-maze",
            public=True,
        )
        ids = [index.add_trial(asked.episode(seed), submitter="alice", db=db) for seed in seeds]
        return evaluations.add(
            db,
            asked,
            task_version="1",
            suite="test" if held_out else "dev",
            suite_version=1,
            held_out=held_out,
            submitter="alice",
            seeds=seeds,
            trial_ids=ids,
        )


def test_evaluations_are_kept_with_their_episodes_and_found(index):
    verdicts = {"sha256:" + "a" * 64: True}
    evaluations = Evaluations(index, verdicts.get)
    dev = add(index, evaluations, held_out=False, seeds=[0, 1, 2])
    read = evaluations.get(dev)
    assert (read.status, read.score.episodes, [r.seed for r in read.rows]) == (
        Status.QUEUED,
        3,
        [0, 1, 2],
    )
    first = read.rows[0].trial
    index.update(first, status="finished", outcome="success", reward=2.0, data_digest="d" * 64)
    index.put_derived(first, Derived(REPLAY, "sha256:" + "a" * 64, 10, "application/json"))
    again = evaluations.get(dev)
    assert again.status is Status.RUNNING
    assert (again.rows[0].outcome, again.rows[0].reward, again.rows[0].verified) == (
        "success",
        2.0,
        True,
    )
    assert (again.score.done, again.score.successes, again.score.success_rate) == (1, 1, None)
    assert evaluations.of_trial(first) == dev and evaluations.trials(dev) == [
        r.trial for r in read.rows
    ]
    found = evaluations.find(EvaluationFilters(task="icreate-maze", suite="dev", commit=COMMIT))
    assert [e.id for e in found.items] == [dev] and found.next is None
    assert evaluations.find(EvaluationFilters(suite="test")).items == []
    assert evaluations.sign(dev, {"signature": "x"}, 100.0)
    assert not evaluations.sign(dev, {"signature": "y"}, 200.0)  # the first signature stays
    assert evaluations.get(dev).signature == {"signature": "x"}
    with pytest.raises(RecordNotFound):
        evaluations.get(dev + 100)


def test_a_held_out_suites_trials_are_the_operators_until_it_is_retired(index):
    evaluations = Evaluations(index, lambda _digest: None)
    public = add(index, evaluations, held_out=False, seeds=[0])
    held = add(index, evaluations, held_out=True, seeds=[123456789, 987654321])
    hidden = evaluations.get(held, reveal=True).rows[0].trial
    seen = evaluations.get(held)  # as its submitter and everyone see it: no episode at all
    assert (seen.hidden, seen.rows, seen.done, seen.compute_seconds) == (True, [], None, None)
    assert [r.seed for r in evaluations.get(held, reveal=True).rows] == [123456789, 987654321]
    with pytest.raises(HeldOut, match="held-out suite"):
        index.readable(hidden)
    assert index.trial(hidden).seed == 123456789  # the lab's own read sees it
    listed = [t.id for t in index.find(Filters(), limit=10).items]
    assert hidden not in listed and evaluations.get(public).rows[0].trial in listed
    assert hidden in [t.id for t in index.find(Filters(held_out=True), limit=10).items]
    assert [t.id for t in index.commit_page(COMMIT).trials] == [
        evaluations.get(public).rows[0].trial
    ]
    assert evaluations.retire("icreate-maze", "test", 1) == 2
    assert evaluations.retired("icreate-maze") == {("test", 1)}
    assert index.readable(hidden).seed == 123456789
    assert [r.seed for r in evaluations.get(held).rows] == [123456789, 987654321]
    later = add(index, evaluations, held_out=True, seeds=[5])  # a retired version is public
    assert evaluations.get(later).rows[0].seed == 5


def test_episodes_verified_on_another_machine_are_counted(index):
    """A cluster's replay says where it ran: an episode replayed on another node than
    the one that ran it counts as verified elsewhere; one replayed on its own node, or
    not verified, does not; without a cluster's verdict there is no count at all."""
    said = {  # verdict digest -> (verified, node)
        "sha256:" + "1" * 64: (True, "ray:bbbb"),
        "sha256:" + "2" * 64: (True, "ray:aaaa"),  # on the node that ran it
        "sha256:" + "3" * 64: (False, "ray:aaaa"),  # elsewhere, but diverged
    }
    evaluations = Evaluations(index, lambda d: said[d][0], replayed_on=lambda d: said[d][1])
    plain = add(index, evaluations, held_out=False, seeds=[7])
    clustered = add(index, evaluations, held_out=False, seeds=[0, 1, 2])
    trials = evaluations.trials(clustered)
    with index.begin() as db:
        for trial, worker in zip(trials, ["ray:aaaa", "ray:aaaa", "ray:bbbb"], strict=True):
            db.execute(sa.update(T).where(T.c.id == trial).values(worker=worker))
    for trial, digest in zip(trials, said, strict=True):
        index.put_derived(trial, Derived(REPLAY, digest, 10, "application/json"))
    rows = evaluations.get(clustered).rows
    assert [r.replayed_elsewhere for r in rows] == [True, False, True]
    assert evaluations.get(clustered).verified_elsewhere == 1
    assert evaluations.get(plain).verified_elsewhere is None
