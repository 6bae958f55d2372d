"""Upgrading an archive's index from labd 0.1's schema: refused until asked, nothing lost."""

from __future__ import annotations

import pytest
import sqlalchemy as sa

from repository import index as current
from repository.errors import SchemaMismatch
from repository.index import SCHEMA_VERSION, Index, connect
from repository.migrate import schema_of, upgrade
from repository.trial import Kind, Order, Outcome, PinnedRecord, Status, TeamRef

NEW_COLUMNS = {"kind", "outcome", "reward", "signature", "data"}
SCHEMA_3_COLUMNS = {"lab_fault"}
SCHEMA_4_COLUMNS = {"away_repository", "away_ref", "away_commit", "step_deadline"}


def before_schema_5(db: sa.Connection) -> None:
    """Take away what schema 5 added: the identities of OpenID providers' people."""
    db.execute(sa.text("DROP TABLE identities"))


def before_schema_4(db: sa.Connection) -> None:
    """Take away what schema 4 added: matches, and a leg's away team on its trial."""
    before_schema_5(db)
    db.execute(sa.text("DROP INDEX ix_trials_away_commit"))
    db.execute(sa.text("DROP TABLE match_legs"))
    db.execute(sa.text("DROP TABLE matches"))
    db.execute(sa.text("DROP TABLE ladder_entries"))
    db.execute(sa.text("DROP TABLE benchmark_run_evaluations"))
    db.execute(sa.text("DROP TABLE benchmark_runs"))
    for column in sorted(SCHEMA_4_COLUMNS):
        db.execute(sa.text(f"ALTER TABLE trials DROP COLUMN {column}"))


def schema_1(url: str) -> None:
    """Write an index as labd 0.1 did: no kind, no outcome; status succeeded or failed."""
    engine = connect(url)
    current.metadata.create_all(engine)
    with engine.begin() as db:  # take away what schema 2 added
        before_schema_4(db)
        for index in (
            "ix_trials_outcome",
            "ix_trials_task_outcome",
            "ix_trials_kind",
            "ix_trials_task_reward",
            "ix_trials_reward",
        ):
            db.execute(sa.text(f"DROP INDEX {index}"))
        for column in sorted(NEW_COLUMNS | SCHEMA_3_COLUMNS):
            db.execute(sa.text(f"ALTER TABLE trials DROP COLUMN {column}"))
    trials = sa.Table("trials", sa.MetaData(), autoload_with=engine)
    base = {
        "repository": "https://example.org/r.git",
        "ref": "main",
        "commit": "a" * 40,
        "task": "icreate-maze",
        "params": {},
        "seed": 0,
        "submitter": "alice",
        "public": True,
        "created": 1.0,
        "attempts": 1,
        "cancel_requested": False,
    }
    rows = [
        {"status": "succeeded", "reason": "reached", "metrics": {"success": True, "reward": 1.0}},
        {"status": "succeeded", "reason": "timed out", "metrics": {"success": False}},
        {"status": "succeeded", "reason": "exited with 0", "metrics": None},
        {"status": "failed", "reason": "controller exited with 1", "metrics": {"success": False}},
        {"status": "cancelled", "reason": "cancelled by alice", "metrics": None},
        {"status": "queued", "reason": "waiting for a worker", "metrics": None},
    ]
    with engine.begin() as db:
        db.execute(sa.insert(current.meta).values(key="schema", value="1"))
        db.execute(sa.insert(trials), [{**base, **row} for row in rows])
    engine.dispose()


def test_an_old_index_is_refused_with_the_command_that_upgrades_it(database_url):
    """Opening a schema-1 index says what it is and to run `labd migrate`, and changes nothing."""
    schema_1(database_url)
    with pytest.raises(SchemaMismatch, match="labd migrate") as caught:
        Index.open(database_url)
    assert (caught.value.found, caught.value.expected) == (1, SCHEMA_VERSION)
    engine = connect(database_url)
    assert schema_of(engine) == 1
    columns = {c["name"] for c in sa.inspect(engine).get_columns("trials")}
    assert not columns & NEW_COLUMNS
    engine.dispose()


def test_the_upgrade_keeps_every_row_and_reads_each_status_anew(database_url):
    """succeeded becomes success or fail by the task's own verdict; failed becomes error."""
    schema_1(database_url)
    engine = connect(database_url)
    done = upgrade(engine)
    assert (done.before, done.after) == (1, SCHEMA_VERSION)
    assert done.changed == {
        "succeeded -> success": 1,
        "succeeded -> fail": 2,
        "failed -> error": 1,
    }
    assert f"upgraded the index from schema 1 to {SCHEMA_VERSION}" in str(done)
    assert upgrade(engine).changed == {}  # a second run does nothing
    engine.dispose()
    index = Index.open(database_url)
    try:
        got = [index.trial(n) for n in range(1, 7)]
    finally:
        index.close()
    assert [(t.status, t.outcome) for t in got] == [
        (Status.FINISHED, Outcome.SUCCESS),
        (Status.FINISHED, Outcome.FAIL),
        (Status.FINISHED, Outcome.FAIL),
        (Status.FINISHED, Outcome.ERROR),
        (Status.CANCELLED, None),
        (Status.QUEUED, None),
    ]
    assert [t.reason for t in got][:4] == [
        "reached",
        "timed out",
        "exited with 0",
        "controller exited with 1",
    ]
    assert got[0].metrics == {"success": True, "reward": 1.0}
    engine = connect(database_url)
    with engine.connect() as db:
        rewards = db.execute(sa.text("SELECT reward FROM trials ORDER BY id")).scalars().all()
    engine.dispose()
    assert rewards == [1.0, None, None, None, None, None]
    assert all(t.kind.value == "trial" for t in got)
    assert all(t.data is None for t in got)  # nothing was pinned before schema 2
    assert not any(t.lab_fault for t in got)  # no error was said to be the lab's before 3


def test_a_schema_2_index_upgrades_to_say_whose_fault_an_error_was(database_url):
    """Schema 2 -> 3 adds lab_fault, false for every trial filed before, and keeps the rest."""
    engine = connect(database_url)
    current.metadata.create_all(engine)
    base = {
        "repository": "https://example.org/r.git",
        "commit": "a" * 40,
        "task": "icreate-maze",
        "params": {},
        "seed": 0,
        "submitter": "alice",
        "public": True,
        "created": 1.0,
        "attempts": 1,
        "cancel_requested": False,
        "kind": "trial",
        "status": "finished",
        "outcome": "error",
        "reason": "its worker was lost 3 times; the lab gave up",
    }
    with engine.begin() as db:
        before_schema_4(db)
        db.execute(sa.text("ALTER TABLE trials DROP COLUMN lab_fault"))
        db.execute(sa.insert(current.meta).values(key="schema", value="2"))
    trials = sa.Table("trials", sa.MetaData(), autoload_with=engine)
    with engine.begin() as db:
        db.execute(sa.insert(trials), [base])
    with pytest.raises(SchemaMismatch, match="labd migrate"):
        Index.open(database_url)
    done = upgrade(engine)
    assert (done.before, done.after, done.changed) == (2, SCHEMA_VERSION, {})
    engine.dispose()
    index = Index.open(database_url)
    try:
        trial = index.trial(1)
    finally:
        index.close()
    assert (trial.outcome, trial.lab_fault, trial.reason) == (Outcome.ERROR, False, base["reason"])


def test_an_upgraded_index_keeps_the_data_a_trial_pins(database_url):
    """The upgrade adds the column of pinned data, so a new trial's pinned records are kept."""
    schema_1(database_url)
    engine = connect(database_url)
    upgrade(engine)
    engine.dispose()
    pinned = PinnedRecord(
        trial=1,
        kind=Kind.TRIAL,
        task="icreate-maze",
        seed=0,
        outcome=Outcome.SUCCESS,
        data_digest="d" * 64,
        digest_topics=["/odom"],
        mcap="sha256:" + "e" * 64,
        size=10,
    )
    index = Index.open(database_url)
    try:
        order = Order(
            repository="https://example.org/knn.git",
            commit="b" * 40,
            task="icreate-maze",
            seed=1,
            public=True,
            data=(pinned,),
        )
        new = index.add_trial(order, submitter="alice")
        assert index.trial(new).data == [pinned]
    finally:
        index.close()


def test_a_schema_3_index_upgrades_to_hold_matches(database_url):
    """Schema 3 → 4 adds the matches and a leg's away team: the trials filed before have
    none, and a leg queued after keeps its away team."""
    engine = connect(database_url)
    current.metadata.create_all(engine)
    with engine.begin() as db:
        before_schema_4(db)
        db.execute(sa.insert(current.meta).values(key="schema", value="3"))
    old = sa.Table("trials", sa.MetaData(), autoload_with=engine)
    with engine.begin() as db:
        db.execute(
            sa.insert(old),
            [
                {
                    "kind": "trial",
                    "repository": "https://example.org/r.git",
                    "commit": "a" * 40,
                    "task": "icreate-maze",
                    "params": {},
                    "seed": 0,
                    "submitter": "alice",
                    "public": True,
                    "status": "queued",
                    "reason": "waiting for a worker",
                    "created": 1.0,
                    "attempts": 0,
                    "cancel_requested": False,
                }
            ],
        )
    with pytest.raises(SchemaMismatch, match="labd migrate"):
        Index.open(database_url)
    done = upgrade(engine)
    assert (done.before, done.after) == (3, SCHEMA_VERSION)
    assert {"matches", "match_legs", "ladder_entries"} <= set(sa.inspect(engine).get_table_names())
    engine.dispose()
    index = Index.open(database_url)
    try:
        assert index.trial(1).away is None
        away = TeamRef(repository="https://example.org/b.git", commit="b" * 40)
        leg = Order(
            repository="https://example.org/a.git",
            commit="c" * 40,
            task="soccer-1v1",
            kind=Kind.MATCH,
            away=away,
            step_deadline=4.0,
        )
        assert index.trial(index.add_trial(leg, submitter="alice")).order == leg
    finally:
        index.close()


def test_a_schema_4_index_upgrades_to_hold_identities(database_url):
    """Schema 4 → 5 adds the identities table; the users and their sessions stay."""
    engine = connect(database_url)
    current.metadata.create_all(engine)
    with engine.begin() as db:
        before_schema_5(db)
        db.execute(sa.insert(current.meta).values(key="schema", value="4"))
    with pytest.raises(SchemaMismatch, match="labd migrate"):
        Index.open(database_url)
    done = upgrade(engine)
    assert (done.before, done.after) == (4, SCHEMA_VERSION)
    assert "identities" in sa.inspect(engine).get_table_names()
    engine.dispose()
