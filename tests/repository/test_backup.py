"""The archive's backup: its index at one moment, its blobs copied once and checked, and a
restore that brings back every row, on SQLite and PostgreSQL, or refuses."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import pytest
import sqlalchemy as sa

from repository import backup, backup_trust, signed_rows
from repository.blobs import BlobStore
from repository.errors import BackupDamaged, BackupError, BackupForged, TargetNotEmpty
from repository.index import SCHEMA_VERSION, Derived, Filters, Index
from repository.migrate import schema_of
from repository.signing import Keyring, record_statement
from repository.tables import (
    derived,
    episodes,
    evaluations,
    metadata,
    reservations,
    trials,
)
from repository.trial import Order
from repository.well_known import REPLAY, SUMMARY, VIDEO
from tests.repository.test_migrate import schema_1

COMMIT = "c0ffee" + "0" * 34


def fill(index: Index, store: BlobStore, keyring: Keyring | None = None) -> dict[str, str]:
    """An archive with a row in every kind of table: users and a token, trials (one a
    rerun, one with a record, logs and derived artifacts), an evaluation with its episode,
    a reservation; its blobs in ``store``. The blobs, by what they are. With a
    ``keyring``, the filed trial is signed as the lab signs it; without, its signature is
    a stand-in (the index keeps whatever JSON it is given)."""
    index.add_user("alice")
    first = _trial(index)
    rerun = _trial(index, rerun_of=first)
    blobs = {
        "mcap": store.put_bytes(b"a record" * 1000),
        "stdout": store.put_bytes(b"tick\n"),
        "summary": store.put_bytes(b"a summary"),
        "replay": store.put_bytes(b'{"verified": true}'),
        "video": store.put_bytes(b"a video, made again at will"),
    }
    index.update(
        first,
        status="finished",
        outcome="success",
        finished=1_700_000_100.0,
        mcap=blobs["mcap"],
        mcap_size=8000,
        stdout=blobs["stdout"],
        metrics={"success": True, "reward": 1.5},
        signature={"statement": {"trial": first}, "key": "ed25519:00", "signature": "x"},
    )
    index.update(rerun, metrics=sa.JSON.NULL)  # a JSON null, kept apart from SQL NULL
    if keyring is not None:
        sign_filed(index, keyring)
    for name, what in ((SUMMARY, "summary"), (REPLAY, "replay"), (VIDEO, "video")):
        size = store.size(blobs[what])
        index.put_derived(first, Derived(name, blobs[what], size, "application/octet-stream"))
    with index.begin() as db:
        evaluation = db.execute(
            sa.insert(evaluations).values(
                task="icreate-maze",
                task_version="1",
                suite="dev",
                suite_version=1,
                held_out=False,
                repository="https://example.org/r.git",
                commit=COMMIT,
                params={},
                submitter="alice",
                created=1.0,
                cancel_requested=False,
            )
        ).inserted_primary_key[0]
        db.execute(
            sa.insert(episodes).values(
                evaluation_id=evaluation, episode=0, seed=2**63 - 1, trial_id=first, hidden=False
            )
        )
        db.execute(
            sa.insert(reservations).values(
                robot="icreate-1",
                user="alice",
                start=10.0,
                end=20.0,
                booked_end=20.0,
                created=1.0,
                nonce="n" * 32,
            )
        )
    return blobs


def sign_filed(index: Index, keyring: Keyring) -> None:
    """Sign each trial that has an outcome as the lab signs a filed record
    (``scheduler.queue``): its row as it stands."""
    with index.begin() as db:
        for row in db.execute(sa.select(trials).where(trials.c.outcome.is_not(None))).all():
            statement = record_statement(
                trial=row.id,
                kind=row.kind,
                repository=row.repository,
                commit=row.commit,
                task=row.task,
                seed=row.seed,
                status=row.status,
                outcome=row.outcome,
                manifest_digest=row.manifest_digest,
                data_digest=row.data_digest,
                digest_topics=row.digest_topics,
                mcap=row.mcap,
                mcap_size=row.mcap_size,
                metrics=row.metrics,
                finished=row.finished,
            )
            signed = keyring.sign(statement).to_json()
            db.execute(sa.update(trials).where(trials.c.id == row.id).values(signature=signed))


def _trial(index: Index, rerun_of: int | None = None) -> int:
    order = Order(
        repository="https://example.org/r.git",
        ref="main",
        commit=COMMIT,
        task="icreate-maze",
        params={"maze_size": 7},
        seed=2**63 - 1,
        public=True,
        rerun_of=rerun_of,
    )
    return index.add_trial(order, submitter="alice")


def rows(url: str) -> dict[str, list[dict[str, Any]]]:
    """Every row of every table, JSON columns as their text (null and NULL apart)."""
    engine = sa.create_engine(url)
    found = {}
    with engine.connect() as db:
        for table in metadata.sorted_tables:
            columns = [
                sa.cast(c, sa.Text).label(c.name) if isinstance(c.type, sa.JSON) else c
                for c in table.columns
            ]
            query = sa.select(*columns).order_by(*table.primary_key.columns)
            found[table.name] = [dict(r._mapping) for r in db.execute(query)]
    engine.dispose()
    for row in found[derived.name]:
        row.pop("created")
    for table in found.values():  # the same JSON, however a database spaces it
        for row in table:
            for name, value in row.items():
                if isinstance(value, str) and value[:1] in "{[":
                    row[name] = json.loads(value)
    return found


def without_remade(found: dict[str, list[dict[str, Any]]]) -> dict[str, list[dict[str, Any]]]:
    """The rows a backup keeps: a video's row is left out (the lab renders it again)."""
    return {
        **found,
        derived.name: [r for r in found[derived.name] if r["name"] in backup.KEPT_DERIVED],
    }


@pytest.fixture
def source(tmp_path: Path) -> tuple[str, BlobStore, dict[str, str]]:
    """A filled archive in SQLite: its URL, its store, its blobs."""
    url = f"sqlite:///{tmp_path / 'source.sqlite'}"
    index = Index.open(url)
    store = BlobStore(str(tmp_path / "source-blobs"))
    blobs = fill(index, store)
    index.close()
    return url, store, blobs


def test_every_row_comes_back_and_new_ids_follow_the_restored_ones(database_url, tmp_path):
    """Backed up from each database and restored into the other kind (SQLite to the
    tested one, the tested one to SQLite): every row the same, JSON null and SQL NULL
    apart, the video's row left out; a new trial gets the next id (PostgreSQL: its
    sequence moved past the restored ids)."""
    index = Index.open(database_url)
    fill(index, BlobStore(str(tmp_path / "blobs")))
    index.close()
    original = rows(database_url)
    shot = backup.snapshot(database_url, tmp_path / "b1" / backup.INDEX_FILE)
    assert shot.rows[trials.name] == 2 and shot.rows[derived.name] == 2
    assert shot.schema == SCHEMA_VERSION

    restored_url = f"sqlite:///{tmp_path / 'restored.sqlite'}"
    engine = sa.create_engine(restored_url)
    backup.restore_index(shot.path, engine)
    engine.dispose()
    assert rows(restored_url) == without_remade(original)

    # back again, into the tested database (emptied first)
    engine = sa.create_engine(database_url)
    metadata.drop_all(engine)
    again = backup.snapshot(restored_url, tmp_path / "b2" / backup.INDEX_FILE)
    backup.restore_index(again.path, engine)
    engine.dispose()
    assert rows(database_url) == without_remade(original)
    index = Index.open(database_url)
    assert _trial(index) == 3
    index.close()


def test_the_snapshot_is_of_one_moment(database_url, tmp_path):
    """A trial filed while the snapshot reads (after its schema, before the trials)
    is in the index and not in the snapshot: every table is read at the same moment."""
    index = Index.open(database_url)
    _trial(index)
    written: list[int] = []

    def write_once(conn: Any, _cursor: Any, statement: str, *_: Any) -> None:
        if conn.engine is not index.writer and not written and "FROM labd_meta" in statement:
            written.append(_trial(index))

    sa.event.listen(sa.engine.Engine, "before_cursor_execute", write_once)
    try:
        shot = backup.snapshot(database_url, tmp_path / "b" / backup.INDEX_FILE)
    finally:
        sa.event.remove(sa.engine.Engine, "before_cursor_execute", write_once)
    assert written == [2], "the snapshot never read its schema"
    assert shot.rows[trials.name] == 1
    assert [t.id for t in index.find(Filters()).items] == [2, 1]
    index.close()


def test_a_restore_into_an_index_that_holds_rows_is_refused(source, database_url, tmp_path):
    """An index with a trial, or only a user, is no target: the refusal says what it
    holds, and nothing is added to it."""
    url, _store, _blobs = source
    shot = backup.snapshot(url, tmp_path / "b" / backup.INDEX_FILE)
    index = Index.open(database_url)
    index.add_user("bob")
    engine = sa.create_engine(database_url)
    with pytest.raises(TargetNotEmpty, match=r"already holds rows of tokens \(1\), users \(1\)"):
        backup.restore_index(shot.path, engine)
    _trial(index)
    with pytest.raises(TargetNotEmpty, match=r"already holds 1 trial\(s\); restore only"):
        backup.restore_index(shot.path, engine)
    assert backup.rows_held(engine) == {"users": 1, "tokens": 1, "trials": 1}
    engine.dispose()
    index.close()


def test_blobs_are_copied_once_each_and_checked(source, tmp_path):
    """The blobs the rows name are copied (not the video's); a second copy copies
    nothing; a blob missing or damaged in the source is named, and the others copied."""
    url, store, blobs = source
    shot = backup.snapshot(url, tmp_path / "b" / backup.INDEX_FILE)
    dest = BlobStore(str(tmp_path / "b" / "blobs"))
    with backup.index_connection(shot.path) as db:
        total = backup.count_named(db)
        done = backup.copy_blobs(backup.named_blobs(db), total, store, dest)
        assert (total, done.copied, done.present, done.unreadable) == (4, 4, 0, {})
        assert not dest.exists(blobs["video"])
        again = backup.copy_blobs(backup.named_blobs(db), total, store, dest)
        assert (again.copied, again.present, again.bytes) == (0, 4, 0)
        assert again.total_bytes == done.total_bytes == done.bytes

        other = BlobStore(str(tmp_path / "other"))
        Path(store.path(blobs["stdout"])).unlink()
        damaged = Path(store.path(blobs["summary"]))
        damaged.chmod(0o644)
        damaged.write_bytes(b"a summary, edited")
        done = backup.copy_blobs(backup.named_blobs(db), total, store, other)
        assert done.copied == 2
        assert done.unreadable == {
            blobs["stdout"]: "missing from the store",
            blobs["summary"]: pytest.approx(done.unreadable[blobs["summary"]]),
        }
        assert done.unreadable[blobs["summary"]].startswith("damaged (its bytes hash to sha256:")
        assert not other.exists(blobs["summary"]) and not other.exists(blobs["stdout"])
        assert backup.owner(db, blobs["stdout"]) == "trial 1's stdout"
        assert backup.owner(db, blobs["summary"]) == "trial 1's summary.json"


def test_a_blob_of_the_wrong_size_in_the_backup_is_copied_again(source, tmp_path):
    """A record whose copy in the backup has another size than the index says is not
    taken as present: it is copied again."""
    url, store, blobs = source
    shot = backup.snapshot(url, tmp_path / "b" / backup.INDEX_FILE)
    dest = BlobStore(str(tmp_path / "blobs"))
    truncated = Path(dest.path(blobs["mcap"]))
    truncated.parent.mkdir(parents=True)
    truncated.write_bytes(b"a rec")
    with backup.index_connection(shot.path) as db:
        done = backup.copy_blobs(backup.named_blobs(db), 4, store, dest)
    assert done.copied == 4
    assert dest.read_bytes(blobs["mcap"]) == b"a record" * 1000


def _manifest(
    folder: Path, schema: int = SCHEMA_VERSION, keyring: Keyring | None = None
) -> backup.Manifest:
    """A manifest of the index in ``folder``, written there; signed by ``keyring`` (the
    backup's own, in ``folder/keys``, unless given)."""
    keyring = keyring or Keyring(folder / backup.KEYS)
    keys = sorted(p.name for p in keyring.folder.iterdir())
    manifest = backup.Manifest(
        labd="0.2.0",
        schema=schema,
        made="2026-01-01T00:00:00+00:00",
        index_sha256=backup.file_sha256(folder / backup.INDEX_FILE),
        rows={"trials": 2},
        blobs=4,
        blob_bytes=8000,
        keys=keys,
        key_sha256={n: backup.file_sha256(keyring.folder / n) for n in keys},
    ).signed(keyring)
    manifest.write(folder)
    return manifest


def test_a_backup_without_its_manifest_changed_or_newer_is_refused(source, tmp_path):
    """No manifest (a backup that did not finish), an index file that changed since, a
    schema newer than this labd's, an older labd's unsigned manifest: each refused,
    saying which."""
    url, _store, _blobs = source
    folder = tmp_path / "b"
    backup.snapshot(url, folder / backup.INDEX_FILE)
    with pytest.raises(BackupDamaged, match=r"no backup\.json"):
        backup.Manifest.read(folder)
    _manifest(folder)
    manifest = backup.Manifest.read(folder)
    manifest.check(folder)
    assert manifest.trials == 2
    index = folder / backup.INDEX_FILE
    data = bytearray(index.read_bytes())
    data[-100] ^= 0x01
    index.write_bytes(bytes(data))
    with pytest.raises(BackupDamaged, match=r"index\.sqlite hashes to sha256:.*was changed"):
        manifest.check(folder)
    newer = _manifest(folder, SCHEMA_VERSION + 1)
    with pytest.raises(BackupError, match=f"schema {SCHEMA_VERSION + 1}, newer than"):
        newer.check(folder)
    (folder / backup.MANIFEST_FILE).write_text('{"format": "something else"}')
    with pytest.raises(BackupDamaged, match=r"not a labd\.backup/2 manifest"):
        backup.Manifest.read(folder)
    (folder / backup.MANIFEST_FILE).write_text('{"format": "labd.backup/1"}')
    with pytest.raises(BackupDamaged, match=r"an older labd's \(labd\.backup/1\), which the lab"):
        backup.Manifest.read(folder)


def test_a_manifest_is_held_to_the_labs_signature(source, tmp_path):
    """A manifest checks with the key that signed it; one with a field changed names the
    field; one signed by another key than the one named, or by none, is refused."""
    url, _store, _blobs = source
    folder = tmp_path / "b"
    backup.snapshot(url, folder / backup.INDEX_FILE)
    lab = Keyring(folder / backup.KEYS)
    manifest = _manifest(folder, keyring=lab)
    keys = backup_trust.KeyFiles.read(folder / backup.KEYS)
    assert keys.signing == lab.current and set(keys.public) == {lab.current}
    manifest.verify(folder, keys.public, lab.current)
    edited = dataclasses.replace(manifest, blobs=5)
    with pytest.raises(BackupForged, match=r"other than the lab's signature of it \(blobs changed"):
        edited.verify(folder, keys.public, lab.current)
    other = Keyring(tmp_path / "other")
    with pytest.raises(BackupForged, match=r"not signed by the lab's key .* but by ed25519:"):
        manifest.signed(other).verify(folder, keys.public, lab.current)
    with pytest.raises(BackupForged, match=r"which is not among the keys given"):
        manifest.signed(other).verify(folder, keys.public, None)
    with pytest.raises(BackupForged, match=r"carries no signature"):
        dataclasses.replace(manifest, signature=None).verify(folder, keys.public, None)


def test_a_backup_of_an_older_schema_is_upgraded_as_it_is_restored(tmp_path, database_url):
    """A backup whose index has schema 1 (labd 0.1, before records were signed) is
    upgraded in a private copy and restored with its statuses split; the backup's own
    file is left as it was."""
    folder = tmp_path / "old"
    folder.mkdir()
    schema_1(backup.sqlite_url(folder / backup.INDEX_FILE))
    _manifest(folder, schema=1)
    before = (folder / backup.INDEX_FILE).read_bytes()
    engine = sa.create_engine(database_url)
    opened = backup_trust.open_backup(folder)
    scratch = tmp_path / "scratch"
    scratch.mkdir()
    with backup_trust.checked_index(opened, scratch) as index:
        assert index.parent.parent == scratch
        counts = backup.restore_index(index, engine)
    assert list(scratch.iterdir()) == []
    assert counts[trials.name] == 6
    assert schema_of(engine) == SCHEMA_VERSION
    with engine.connect() as db:
        statuses = sorted(db.execute(sa.select(trials.c.status, trials.c.outcome)).all(), key=str)
    engine.dispose()
    assert ("finished", "success") in statuses and ("finished", "error") in statuses
    assert (folder / backup.INDEX_FILE).read_bytes() == before


def test_no_index_there_is_said(tmp_path):
    """A database without a labd index is no source for a backup."""
    with pytest.raises(BackupError, match="holds no labd index"):
        backup.snapshot(f"sqlite:///{tmp_path / 'empty.sqlite'}", tmp_path / "b.sqlite")
    assert not (tmp_path / "b.sqlite").exists()


def test_every_row_is_held_to_its_signature(tmp_path):
    """A trial or an evaluation whose row says other than the lab signed is named, with
    what differs; a row signed for another trial is refused; a filed record without a
    signature is refused unless it finished before the first signed one (an older
    labd's); unsigned errors and queued trials are taken as they are."""
    lab = Keyring(tmp_path / "keys")
    index = Index.open(f"sqlite:///{tmp_path / 'index.sqlite'}")
    fill(index, BlobStore(str(tmp_path / "blobs")), lab)
    with index.begin() as db:
        evaluation = db.execute(sa.select(evaluations)).one()
        said = {
            "schema": "labd.evaluation/2",
            "evaluation": evaluation.id,
            "repository": evaluation.repository,
            "commit": evaluation.commit,
            "task": evaluation.task,
            "suite": evaluation.suite,
            "suite_version": evaluation.suite_version,
            "rows": [{"episode": 0, "trial": 1, "status": "finished", "outcome": "success"}],
        }
        signed = lab.sign(said).to_json()
        db.execute(sa.update(evaluations).values(signature=signed))
    keys = {lab.current: lab.public_keys()[lab.current]}

    def problems() -> list[str]:
        with index.engine.connect() as db:
            return signed_rows.check(db, keys)

    assert problems() == []
    index.update(1, outcome="fail", metrics={"success": True, "reward": 9.0})
    assert problems() == [
        "trial 1: its metrics is {'success': True, 'reward': 9.0}, the lab signed"
        " {'success': True, 'reward': 1.5}",
        "trial 1: its outcome is 'fail', the lab signed 'success'",
        "evaluation 1: its episode trial 1 has the outcome 'fail', the lab signed 'success'",
    ]
    index.update(1, outcome="success", metrics={"success": True, "reward": 1.5})
    assert problems() == []

    second = _trial(index)  # a record filed after the first signed one, unsigned
    index.update(second, status="finished", outcome="success", finished=1_700_000_200.0)
    assert problems() == [
        "trial 3: a filed record (success) without the lab's signature, filed after the"
        " lab signed its records"
    ]
    index.update(second, finished=1_700_000_000.0)  # before it: an older labd's
    assert problems() == []
    index.update(second, outcome="error", finished=1_700_000_200.0)  # a lost lease
    assert problems() == []

    first = index.trial(1).signature
    index.update(second, outcome="success", signature=first)  # trial 1's, copied
    assert "trial 3: its trial is 3, the lab signed 1" in problems()
    other = Keyring(tmp_path / "other")
    index.update(second, signature=other.sign({"schema": "labd.record/2", "trial": 3}).to_json())
    assert problems()[0].startswith(
        f"trial 3: its signature does not check (signed with key {other.current}"
    )
    index.close()
