"""The SQLite index's files watched (``repository.wal``): a WAL deleted or a database
replaced under an open index stops its writes, after saving what the deleted WAL held."""

from __future__ import annotations

import logging
import os
import sqlite3
import subprocess
import sys

import pytest

from repository.errors import IndexLost
from repository.index import Index


@pytest.fixture
def sqlite_index(tmp_path):
    sqlite_index = Index.open(f"sqlite:///{tmp_path / 'index.sqlite'}")
    yield sqlite_index
    sqlite_index.close()


def test_a_deleted_wal_stops_writes_and_its_content_is_saved(sqlite_index, tmp_path, caplog):
    """Deleting the WAL of an open index refuses the next write (and every later one, and
    ``check``) with a reason naming the file, logs it once as critical, and leaves what
    the WAL held in the database file itself."""
    sqlite_index.add_user("alice")
    wal = tmp_path / "index.sqlite-wal"
    os.unlink(wal)
    with caplog.at_level(logging.CRITICAL, "repository.index"), pytest.raises(IndexLost) as lost:
        sqlite_index.add_user("bob")
    assert f"{wal} was deleted or replaced" in str(lost.value)
    assert "nothing is lost" in str(lost.value)
    with pytest.raises(IndexLost):
        sqlite_index.check()
    assert [r.levelname for r in caplog.records] == ["CRITICAL"]
    # another process reads the database file alone (no WAL): alice is in it
    read = "import sqlite3, sys; print(sqlite3.connect(sys.argv[1]).execute('select name from users').fetchall())"
    copy = tmp_path / "copy.sqlite"
    copy.write_bytes((tmp_path / "index.sqlite").read_bytes())
    out = subprocess.run(
        [sys.executable, "-c", read, str(copy)], capture_output=True, text=True, check=True
    )
    assert out.stdout.strip() == "[('alice',)]"


def test_a_replaced_database_stops_writes(sqlite_index, tmp_path):
    """A database file replaced under the open index (a restore over a running lab) is
    refused the same way."""
    db = tmp_path / "index.sqlite"
    other = tmp_path / "other.sqlite"
    sqlite3.connect(other).close()
    os.replace(other, db)
    with pytest.raises(IndexLost, match=r"index\.sqlite was deleted or replaced"):
        sqlite_index.add_user("bob")


def test_an_index_left_alone_keeps_writing(sqlite_index):
    """Writes, closes and reopens of other connections never trip the check (SQLite
    itself does not delete the WAL while the index holds its connection)."""
    for n in range(5):
        sqlite_index.add_user(f"u{n}")
        sqlite_index.engine.dispose()
        sqlite_index.writer.dispose()
    sqlite_index.check()
    assert sqlite_index.user("u4").name == "u4"
