"""The archive's index: users and tokens, the commit page, schema checks."""

from __future__ import annotations

import pytest
import sqlalchemy as sa

from repository.errors import ArchiveError, RecordNotFound, SchemaMismatch
from repository.index import Filters, Sort
from repository.tables import meta
from repository.trial import Kind, Order, Outcome, Status, TeamRef


def trial(index, commit, *, rerun_of=None, seed=0):
    order = Order(
        repository="https://example.org/r.git",
        commit=commit,
        task="icreate-maze",
        params={"maze_size": 7},
        seed=seed,
        public=True,
        rerun_of=rerun_of,
    )
    return index.add_trial(order, submitter="alice")


def test_tokens_find_their_user_and_only_a_hash_is_kept(index):
    """A token names its user; the database never holds the token itself."""
    token = index.add_user("alice")
    assert index.user_by_token(token).name == "alice"
    assert index.user_by_token(token + "x") is None
    with index.engine.connect() as db:
        stored = db.execute(sa.select(index.users.c.token_sha256)).scalar()
    assert token not in stored
    with pytest.raises(ArchiveError, match="exists already"):
        index.add_user("alice")
    with pytest.raises(ArchiveError, match="user name"):
        index.add_user("no spaces")


def test_commit_page_groups_reruns_and_counts_verdicts(index):
    """A commit's page lists its trials with their reruns and how many reproduced."""
    commit = "c0ffee" + "0" * 34
    original = trial(index, commit)
    other = trial(index, commit, seed=1)
    good = trial(index, commit, rerun_of=original)
    bad = trial(index, commit, rerun_of=original)
    index.update(good, reproduced=True, status="finished", outcome="success")
    index.update(bad, reproduced=False, divergence="diverged at tick 3 on /odom")
    trial(index, "d" * 40)
    page = index.commit_page("c0ffee")
    assert page.commit == commit
    assert [t.id for t in page.trials] == [other, original]
    assert sorted(r.id for r in page.reruns[original]) == [good, bad]
    assert page.rerun_counts == {"reproduced": 1, "diverged": 1, "pending": 0}


def test_commit_prefixes_are_checked(index):
    """Short, non-hex, unknown and ambiguous commits get errors that say so."""
    trial(index, "abcd" + "1" * 36)
    trial(index, "abcd" + "2" * 36)
    with pytest.raises(ArchiveError, match="4 to 40 hexadecimal"):
        index.commit_page("ab")
    with pytest.raises(ArchiveError, match="4 to 40 hexadecimal"):
        index.commit_page("zzzzzz")
    with pytest.raises(RecordNotFound):
        index.commit_page("ffff")
    with pytest.raises(ArchiveError, match="ambiguous"):
        index.commit_page("abcd")
    assert index.commit_page("abcd1").commit == "abcd" + "1" * 36


def test_a_database_of_another_schema_is_refused(index):
    """Opening a database written by another schema version fails with a clear error."""
    with index.begin() as db:
        db.execute(sa.update(meta).values(value="99"))
    with pytest.raises(SchemaMismatch, match="schema 99, from a newer labd"):
        index.create()


def test_trial_not_found(index):
    with pytest.raises(RecordNotFound, match="no trial '42'"):
        index.trial(42)


def test_records_come_back_typed(index):
    """A trial reads back as the typed record: enums, datetimes, its request as given."""
    trial_id = trial(index, "e" * 40, seed=5)
    record = index.trial(trial_id)
    assert record.status is Status.QUEUED and record.outcome is None
    assert record.kind is Kind.TRIAL
    assert record.created.tzinfo is not None
    assert (record.seed, record.params) == (5, {"maze_size": 7})
    index.update(trial_id, status="finished", outcome="fail", metrics={"reward": 0.25})
    done = index.trial(trial_id)
    assert done.outcome is Outcome.FAIL and done.reward == 0.25
    assert [t.id for t in index.find(Filters(outcome=Outcome.FAIL)).items] == [trial_id]
    assert index.find(Filters(outcome=Outcome.SUCCESS)).items == []


def finish(index, trial_id, outcome, reward):
    index.update(
        trial_id,
        status="finished",
        outcome=outcome,
        reward=reward,
        metrics=None if reward is None else {"reward": reward},
    )


def test_sorting_by_reward(index):
    """Lists sort by reward, best first and none last (a page at an offset)."""
    a, b = "a" * 40, "b" * 40
    ids = {
        (a, 0): trial(index, a, seed=0),
        (a, 1): trial(index, a, seed=1),
        (b, 0): trial(index, b, seed=0),
        (b, 1): trial(index, b, seed=1),
    }
    finish(index, ids[a, 0], "success", 0.9)
    finish(index, ids[a, 1], "fail", 0.1)
    finish(index, ids[b, 0], "success", 0.5)
    finish(index, ids[b, 1], "success", None)
    rerun = trial(index, b, rerun_of=ids[b, 0])
    finish(index, rerun, "fail", 0.0)
    best = index.find(Filters(task="icreate-maze"), order=Sort.REWARD, limit=3)
    assert [t.id for t in best.items] == [ids[a, 0], ids[b, 0], ids[a, 1]]
    rest = index.find(Filters(task="icreate-maze"), order=Sort.REWARD, limit=3, offset=3)
    assert [t.id for t in rest.items] == [rerun, ids[b, 1]]


def test_a_commit_s_page_and_list_hold_the_legs_it_played_away(index):
    """A match's leg is its home team's trial and its away team's too: the away commit's
    page and its trials list it, and name both repositories' parts it played."""
    home, away = "a" * 40, "b" * 40
    leg = Order(
        repository="https://example.org/home.git",
        commit=home,
        task="soccer-1v1",
        kind=Kind.MATCH,
        away=TeamRef(repository="https://example.org/away.git", commit=away),
    )
    leg_id = index.add_trial(leg, submitter="alice")
    own = index.add_trial(
        Order(repository="https://example.org/away.git", commit=away, task="soccer-1v1"),
        submitter="alice",
    )
    page = index.commit_page(away[:8])
    assert (page.commit, [t.id for t in page.trials]) == (away, [own, leg_id])
    assert page.repositories == ["https://example.org/away.git"]
    assert [t.id for t in index.find(Filters(commit=away[:6])).items] == [own, leg_id]
    assert [t.id for t in index.commit_page(home).trials] == [leg_id]
