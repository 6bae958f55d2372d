"""The persistent queue: claiming, leases, fair share, quotas, cancel (SQLite and PostgreSQL)."""

from __future__ import annotations

import threading

import pytest

from repository.index import Filters
from repository.trial import Filing, Order, Outcome, Status
from scheduler.errors import NotYours, QuotaExceeded
from scheduler.queue import Cancel, Queue, QueueConfig

COMMIT = "a" * 40


@pytest.fixture
def queue(clocked_index):
    return Queue(clocked_index, QueueConfig(lease=30.0, max_attempts=2))


def submit(queue, user, *, public=True, commit=COMMIT, seed=0):
    order = Order(
        repository="https://example.org/r.git",
        ref="main",
        commit=commit,
        task="icreate-maze",
        seed=seed,
        public=public,
    )
    return queue.submit(user, order)


def make_user(clocked_index, name, **limits):
    clocked_index.add_user(name, **limits)
    return clocked_index.user(name)


def test_a_claimed_trial_is_running_and_no_other_worker_gets_it(clocked_index, queue):
    """A claim moves the oldest queued trial to running under that worker, once."""
    alice = make_user(clocked_index, "alice")
    first = submit(queue, alice)
    claim = queue.claim("w1")
    assert claim is not None and claim.id == first and claim.attempt == 1
    assert clocked_index.trial(first).status is Status.RUNNING
    assert clocked_index.trial(first).worker == "w1"
    assert queue.claim("w2") is None


def test_public_repositories_go_first(clocked_index, queue):
    """A public repository's trial is claimed before an older private one."""
    alice = make_user(clocked_index, "alice", max_running=5)
    private = submit(queue, alice, public=False)
    public = submit(queue, alice, public=True)
    assert queue.claim("w").id == public
    assert queue.claim("w").id == private


def test_fair_share_between_users(clocked_index, queue):
    """A user with a trial running waits behind another user's first trial."""
    alice = make_user(clocked_index, "alice", max_running=5)
    bob = make_user(clocked_index, "bob", max_running=5)
    a1, a2, a3 = (submit(queue, alice, seed=s) for s in range(3))
    b1 = submit(queue, bob)
    order = [queue.claim("w").id for _ in range(4)]
    assert order == [a1, b1, a2, a3]


def test_per_user_running_limit(clocked_index, queue):
    """A user at their limit of running trials gets no more until one ends."""
    alice = make_user(clocked_index, "alice", max_running=1)
    first = submit(queue, alice)
    second = submit(queue, alice)
    assert queue.claim("w1").id == first
    assert queue.claim("w2") is None
    assert queue.finish(first, "w1", Filing.success("done"))
    assert queue.claim("w2").id == second


def test_daily_limit(clocked_index, queue, clock):
    """Submissions past the daily limit are refused until 24 hours have passed."""
    alice = make_user(clocked_index, "alice", max_daily=2)
    submit(queue, alice)
    submit(queue, alice)
    with pytest.raises(QuotaExceeded, match="daily limit"):
        submit(queue, alice)
    clock.now += 86401
    submit(queue, alice)


def test_a_lost_worker_s_trial_goes_back_to_the_queue(clocked_index, queue, clock):
    """When the lease runs out without a heartbeat, another worker gets the trial."""
    alice = make_user(clocked_index, "alice")
    trial = submit(queue, alice)
    assert queue.claim("dead").id == trial
    clock.now += 20
    assert queue.heartbeat(trial, "dead")  # renewed: 30 s from now
    clock.now += 29
    assert queue.claim("other") is None
    clock.now += 2
    claim = queue.claim("other")
    assert claim.id == trial and claim.attempt == 2
    # the dead worker comes back: it may neither renew nor file the trial
    assert not queue.heartbeat(trial, "dead")
    assert not queue.finish(trial, "dead", Filing.fail("late"))
    assert queue.finish(trial, "other", Filing.success("ok"))
    done = clocked_index.trial(trial)
    assert (done.status, done.outcome, done.reason) == (Status.FINISHED, Outcome.SUCCESS, "ok")


def test_a_trial_lost_too_often_fails(clocked_index, queue, clock):
    """After max_attempts lost leases the trial is an error with the reason, not requeued."""
    alice = make_user(clocked_index, "alice")
    trial = submit(queue, alice)
    for _ in range(2):
        assert queue.claim("w").id == trial
        clock.now += 31
    assert queue.claim("w") is None
    row = clocked_index.trial(trial)
    assert (row.status, row.outcome) == (Status.FINISHED, Outcome.ERROR)
    assert "lost 2 times" in row.reason


def test_cancel_queued_and_running(clocked_index, queue):
    """A queued trial is cancelled at once; a running one is flagged for its worker."""
    alice = make_user(clocked_index, "alice", max_running=5)
    bob = make_user(clocked_index, "bob")
    queued = submit(queue, alice)
    running = submit(queue, alice)
    assert queue.claim("w").id == queued  # oldest first
    assert queue.cancel(running, alice) is Cancel.CANCELLED
    assert clocked_index.trial(running).status is Status.CANCELLED
    with pytest.raises(NotYours, match="only they may cancel"):
        queue.cancel(queued, bob)
    assert queue.heartbeat(queued, "w")
    assert queue.cancel(queued, alice) is Cancel.STOPPING
    assert not queue.heartbeat(queued, "w")  # the worker is told to stop
    assert queue.finish(queued, "w", Filing.cancelled("cancelled while it ran"))
    assert queue.cancel(queued, alice) is Cancel.ENDED  # nothing left to do
    assert queue.cancel(running, alice) is Cancel.ENDED


def test_release_worker_requeues_at_once(clocked_index, queue):
    """A restarted server hands back its dead predecessor's trials without waiting."""
    alice = make_user(clocked_index, "alice")
    trial = submit(queue, alice)
    queue.claim("host:123/local-1")
    assert queue.running_workers() == {"host:123/local-1"}
    assert queue.release_worker("host:123/") == [trial]
    assert clocked_index.trial(trial).status is Status.QUEUED
    assert "requeued" in clocked_index.trial(trial).reason


def test_concurrent_claims_never_share_a_trial(clocked_index, queue):
    """Workers claiming at once on threads each get a different trial."""
    alice = make_user(clocked_index, "alice", max_running=100)
    ids = {submit(queue, alice, seed=s) for s in range(12)}
    got: list[int] = []
    lock = threading.Lock()

    def work(name):
        while (claim := queue.claim(name)) is not None:
            with lock:
                got.append(claim.id)

    threads = [threading.Thread(target=work, args=(f"w{n}",)) for n in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert sorted(got) == sorted(ids)


def test_lists_filter_and_paginate(clocked_index, queue):
    """Lists are newest first, filtered, and their cursor pages through all rows."""
    alice = make_user(clocked_index, "alice", max_running=100)
    bob = make_user(clocked_index, "bob")
    mine = [submit(queue, alice, seed=s, commit=("b" * 39 + str(s % 2))) for s in range(7)]
    submit(queue, bob)
    seen, before = [], None
    while True:
        page = clocked_index.find(Filters(submitter="alice"), limit=3, before=before)
        seen += [r.id for r in page.items]
        if page.next is None:
            break
        before = page.next
    assert seen == sorted(mine, reverse=True)
    odd = clocked_index.find(Filters(commit="b" * 39 + "1")).items
    assert [r.id for r in odd] == [m for m in reversed(mine) if (mine.index(m) % 2)]
    assert len(clocked_index.find(Filters(commit="bbbb")).items) == 7
    assert clocked_index.find(Filters(status=Status.RUNNING)).items == []


def test_concurrent_submissions_and_claims_all_land(clocked_index, queue):
    """API threads submitting while workers claim: no "database is locked", and every trial
    submitted is claimed exactly once."""
    alice = make_user(clocked_index, "alice", max_running=1000)
    errors: list[BaseException] = []
    claimed: list[int] = []
    submitted = threading.Event()

    def submitter(n):
        try:
            for s in range(10):
                submit(queue, alice, seed=n * 100 + s)
        except BaseException as err:
            errors.append(err)

    def worker(name):
        try:
            while True:
                last_round = submitted.is_set()  # then a claim of None means none is left
                claim = queue.claim(name)
                if claim is not None:
                    claimed.append(claim.id)
                elif last_round:
                    return
        except BaseException as err:
            errors.append(err)

    submitters = [threading.Thread(target=submitter, args=(n,)) for n in range(4)]
    workers = [threading.Thread(target=worker, args=(f"w{n}",)) for n in range(2)]
    for t in submitters + workers:
        t.start()
    for t in submitters:
        t.join()
    submitted.set()
    for t in workers:
        t.join()
    assert errors == []
    rows = clocked_index.find(Filters(submitter="alice"), limit=500).items
    assert len(rows) == 40
    assert sorted(claimed) == sorted(r.id for r in rows)
    assert {r.status for r in rows} == {Status.RUNNING}


def test_concurrent_claims_keep_the_running_limit(clocked_index, queue):
    """Workers claiming at once never give a submitter more trials than their limit."""
    alice = make_user(clocked_index, "alice", max_running=2)
    for s in range(6):
        submit(queue, alice, seed=s, public=bool(s % 2))
    got: list[int] = []
    lock = threading.Lock()

    def work(name):
        claim = queue.claim(name)
        if claim is not None:
            with lock:
                got.append(claim.id)

    threads = [threading.Thread(target=work, args=(f"w{n}",)) for n in range(6)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(got) == 2
    assert len(clocked_index.find(Filters(status=Status.RUNNING)).items) == 2


def test_concurrent_submissions_keep_the_daily_limit(clocked_index, queue):
    """Submitting from many threads at once never passes the daily limit."""
    alice = make_user(clocked_index, "alice", max_daily=5)
    accepted: list[int] = []
    refused: list[Exception] = []
    lock = threading.Lock()

    def send(seed):
        try:
            trial = submit(queue, alice, seed=seed)
        except QuotaExceeded as err:
            with lock:
                refused.append(err)
        else:
            with lock:
                accepted.append(trial)

    threads = [threading.Thread(target=send, args=(s,)) for s in range(12)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert (len(accepted), len(refused)) == (5, 7)


def test_a_batch_of_episodes_is_queued_whole_and_shares_the_queue(clocked_index, queue):
    """A 50-episode batch (an evaluation's) is queued all or none within the daily limit;
    another user's trial submitted while it runs is the next one claimed, not the 51st."""
    alice = make_user(clocked_index, "alice", max_running=4, max_daily=60)
    bob = make_user(clocked_index, "bob")
    common = Order(
        repository="https://example.org/r.git",
        ref="main",
        commit=COMMIT,
        task="icreate-maze",
        public=True,
    )
    batch = [common.episode(seed) for seed in range(50)]
    ids = queue.submit_many(alice, batch, then=lambda _db, ids: ids)
    assert [clocked_index.trial(t).seed for t in ids] == list(range(50))
    with pytest.raises(QuotaExceeded, match="these 11 would take it past the daily limit of 60"):
        queue.submit_many(alice, batch[:11], then=lambda _db, ids: ids)
    assert (
        len(clocked_index.find(Filters(submitter="alice"), limit=100).items) == 50
    )  # none of the 11
    running = [queue.claim(f"w{n}") for n in range(2)]
    assert [c.id for c in running if c] == ids[:2]
    theirs = submit(queue, bob)
    claim = queue.claim("w3")
    assert claim is not None and claim.id == theirs
