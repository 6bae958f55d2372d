"""A backup of the archive: its index as one SQLite file, its blobs, and a manifest.

A backup folder holds ``index.sqlite`` (every row of the index, in this labd's schema),
``blobs/`` (a blob store: the blobs those rows name) and, written last, ``backup.json``
(``Manifest``: the labd and schema versions, when, the rows per table, the sha256 of
the index file and of each key file), signed with the lab's key. A folder without its
manifest is a backup that did not finish.

A backup holds the lab's signing key and secrets, and a restore puts what it holds into a
lab, so neither trusts a folder it did not make, nor a link in one
(``repository.backup_trust``).

Taken while the lab runs, it is consistent because of the order of its steps and the
archive's own rule that a blob is stored before any row names it:

1. ``snapshot``: the whole index is read in one transaction (SQLite: one read
   transaction, which in WAL mode sees one moment while writers go on; PostgreSQL:
   ``REPEATABLE READ``, read only) and written to a new SQLite file, renamed into place
   once whole;
2. ``copy_blobs``: the blobs those rows name (``named_blobs``), each checked against its
   name as it is read; blobs are immutable, so one already in the backup is not copied
   again (a second backup into the same folder copies only what is new).

Derived artifacts that the lab makes again when asked (a rendered video, an export)
are left out, rows and blobs: only the page summary and the replay's verdict are kept.

``restore_index`` puts the rows into another database (SQLite or PostgreSQL; an empty
one only, ``TargetNotEmpty`` otherwise) in one transaction, then moves PostgreSQL's id
sequences past the ids restored. A backup of an older schema is upgraded
(``repository.migrate``) in a scratch copy first; one of a newer schema is refused.
"""

from __future__ import annotations

import contextlib
import datetime as dt
import hashlib
import json
import os
from collections.abc import Callable, Iterator, Mapping
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import sqlalchemy as sa
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PublicKey
from sqlalchemy.engine import Connection, Engine
from sqlalchemy.pool import NullPool

from repository import nofollow
from repository.blobs import CHUNK_SIZE, BlobStore
from repository.digests import canonical_json
from repository.errors import (
    ArchiveError,
    BackupDamaged,
    BackupError,
    BackupForged,
    BlobCorrupt,
    BlobNotFound,
    TargetNotEmpty,
)
from repository.index import SCHEMA_VERSION
from repository.masking import mask_url
from repository.migrate import schema_of, upgrade
from repository.signing import SIGNING, Keyring, Signature, SignatureError, verify
from repository.tables import derived, meta, metadata, trials
from repository.units import MiB
from repository.well_known import REPLAY, SUMMARY

FORMAT = "labd.backup/2"  # what a manifest says it is: /2 is signed by the lab's key
UNSIGNED = "labd.backup/1"  # an older labd's manifest, which nothing signed
INDEX_FILE = "index.sqlite"
MANIFEST_FILE = "backup.json"
BLOBS = "blobs"
KEYS = "keys"
GIT = "git"
KEPT_DERIVED = frozenset({SUMMARY, REPLAY})  # the others (video, exports) are made again
BATCH = 1000  # rows read and written at a time

Progress = Callable[[int, int, int], None]  # blobs done, blobs in all, bytes copied


def _copy_metadata() -> sa.MetaData:
    """The index's tables, their JSON columns keeping SQL NULL as NULL (the lab's own
    tables write None as JSON ``null``; both read back as None)."""
    copy = sa.MetaData()
    for table in metadata.sorted_tables:
        table.to_metadata(copy)
    for table in copy.tables.values():
        for column in table.columns:
            if isinstance(column.type, sa.JSON):
                column.type = sa.JSON(none_as_null=True)
    return copy


TABLES = _copy_metadata()


# -- the manifest --------------------------------------------------------------------------


@dataclass(frozen=True)
class Manifest:
    """What ``backup.json`` says of a finished backup, and the lab's signature of it."""

    labd: str  # the version that made it
    schema: int  # of its index
    made: str  # when its index was read (ISO 8601, UTC)
    index_sha256: str  # of index.sqlite: a changed file is refused
    rows: dict[str, int]  # per table
    blobs: int  # distinct blobs its rows name, all in blobs/
    blob_bytes: int
    keys: list[str] = field(default_factory=list)  # files of keys/
    git: list[str] = field(default_factory=list)  # hosted repositories, USER/NAME
    key_sha256: dict[str, str] = field(default_factory=dict)  # each file of keys/
    format: str = FORMAT
    signature: dict[str, Any] | None = None  # the lab's, over every other field

    @property
    def trials(self) -> int:
        return self.rows.get(trials.name, 0)

    def fields(self) -> dict[str, Any]:
        """Every field but the signature: what the lab signs."""
        found = asdict(self)
        del found["signature"]
        return found

    def signed(self, keyring: Keyring) -> Manifest:
        """The manifest with the signature of ``keyring``'s current key."""
        return replace(self, signature=keyring.sign(self.fields()).to_json())

    def write(self, folder: Path) -> Path:
        """Write it as ``folder/backup.json`` (0600), whole or not at all (a renamed file)."""
        path = folder / MANIFEST_FILE
        tmp = folder / f".{MANIFEST_FILE}.{os.getpid()}"
        tmp.unlink(missing_ok=True)
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, nofollow.FILE)
        with os.fdopen(fd, "w") as out:
            json.dump(asdict(self), out, indent=2, sort_keys=True)
            out.write("\n")
            out.flush()
            os.fsync(out.fileno())
        tmp.replace(path)
        _fsync_folder(folder)
        return path

    @classmethod
    def read(cls, folder: Path) -> Manifest:
        """The manifest of the backup in ``folder`` (read not through a link):
        BackupDamaged if it has none, or one that is not a labd backup's, or an older
        labd's that nothing signed."""
        path = folder / MANIFEST_FILE
        if not folder.is_dir():
            raise BackupError(f"{folder} is not a folder")
        if not path.is_file() or path.is_symlink():
            raise BackupDamaged(
                str(folder), f"no {MANIFEST_FILE} (a backup that did not finish, or no backup)"
            )
        try:
            data = json.loads(nofollow.read_bytes(path))
            if data.get("format") == UNSIGNED:
                raise BackupDamaged(
                    str(folder),
                    f"its {MANIFEST_FILE} is an older labd's ({UNSIGNED}), which the lab did not"
                    " sign, so nothing says the backup is as the lab made it: back the lab up"
                    " again with this labd",
                )
            if data.get("format") != FORMAT:
                raise BackupDamaged(str(folder), f"{MANIFEST_FILE} is not a {FORMAT} manifest")
            fields = {f: data[f] for f in cls.__dataclass_fields__ if f in data}
            found = cls(**fields)
            int(found.schema)
        except (ValueError, TypeError, AttributeError, UnicodeDecodeError, OSError) as err:
            raise BackupDamaged(str(folder), f"{MANIFEST_FILE} cannot be read ({err})") from None
        return found

    def verify(self, folder: Path, keys: Mapping[str, Ed25519PublicKey], by: str | None) -> None:
        """BackupForged unless the lab signed this manifest, as it is, with one of
        ``keys`` (with ``by``: with that key, the backup's signing key)."""
        if not self.signature:
            raise BackupForged(str(folder), f"{MANIFEST_FILE} carries no signature of the lab's")
        try:
            signature = Signature.from_json(self.signature)
        except SignatureError as err:
            raise BackupForged(str(folder), f"the signature of {MANIFEST_FILE}: {err}") from None
        if by is not None and signature.key != by:
            raise BackupForged(
                str(folder),
                f"{MANIFEST_FILE} is not signed by the lab's key ({by}, keys/{SIGNING}) but by"
                f" {signature.key}",
            )
        try:
            verify(signature, keys)
        except SignatureError as err:
            raise BackupForged(
                str(folder), f"the signature of {MANIFEST_FILE} does not hold: {err}"
            ) from None
        signed = {k: v for k, v in signature.statement.items() if k != "key"}
        ours = self.fields()
        changed = sorted(
            k
            for k in set(signed) | set(ours)
            if canonical_json(signed.get(k)) != canonical_json(ours.get(k))
        )
        if changed:
            raise BackupForged(
                str(folder),
                f"{MANIFEST_FILE} says other than the lab's signature of it ({', '.join(changed)}"
                " changed since the backup was made)",
            )

    def check(self, folder: Path) -> None:
        """Refuse a backup whose index file is not the one the manifest names, or whose
        schema this labd cannot read."""
        index = folder / INDEX_FILE
        if not index.is_file() or index.is_symlink():
            raise BackupDamaged(str(folder), f"no {INDEX_FILE}")
        actual = nofollow.sha256(index)
        if actual != self.index_sha256:
            raise BackupDamaged(
                str(folder),
                f"{INDEX_FILE} hashes to {actual}, the manifest says {self.index_sha256}:"
                " the file was changed or damaged since the backup",
            )
        if self.schema > SCHEMA_VERSION:
            raise BackupError(
                f"the backup in {folder} has schema {self.schema}, newer than this labd's"
                f" {SCHEMA_VERSION} (labd {self.labd} made it): restore it with that labd"
            )


def file_sha256(path: Path) -> str:
    sha = hashlib.sha256()
    with path.open("rb") as stream:
        while chunk := stream.read(MiB):
            sha.update(chunk)
    return f"sha256:{sha.hexdigest()}"


def _fsync_folder(folder: Path) -> None:
    fd = os.open(folder, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def sqlite_url(path: Path) -> str:
    return f"sqlite:///{path.resolve()}"


# -- the index -----------------------------------------------------------------------------


@dataclass(frozen=True)
class Snapshot:
    """The index as one moment saw it, in a SQLite file."""

    path: Path
    schema: int
    made: str
    rows: dict[str, int]


def snapshot(url: str, path: Path) -> Snapshot:
    """Copy every row of the index at ``url`` (this labd's schema) into a new SQLite file
    at ``path``, in one read transaction; the file appears only once whole.

    ArchiveError if there is no index at ``url`` or it has another schema.
    """
    database = sa.make_url(url).database
    if url.startswith("sqlite") and database and Path(database).resolve() == path.resolve():
        raise BackupError(f"{path} is the index itself; back it up into another folder")
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.part")
    tmp.unlink(missing_ok=True)
    # made 0600 before SQLite opens it (its journal takes the file's mode): it holds
    # password and token hashes, and held-out seeds
    os.close(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, nofollow.FILE))
    out = sa.create_engine(sqlite_url(tmp), poolclass=NullPool)
    rows: dict[str, int] = {}
    try:
        TABLES.create_all(out)
        with _read_one_moment(url) as source, out.begin() as dest:
            made = dt.datetime.now(dt.UTC).isoformat(timespec="seconds")
            schema = None
            if sa.inspect(source).has_table(meta.name):
                found = source.execute(sa.select(meta.c.value).where(meta.c.key == "schema"))
                schema = found.scalar()
            if schema is None:
                raise BackupError(f"{_shown(url)} holds no labd index")
            if int(schema) != SCHEMA_VERSION:
                raise BackupError(
                    f"the index at {_shown(url)} has schema {schema}, this labd's is"
                    f" {SCHEMA_VERSION}: back it up with the labd that serves it"
                    + (
                        " (or upgrade it first: labd migrate)"
                        if int(schema) < SCHEMA_VERSION
                        else ""
                    )
                )
            for table in TABLES.sorted_tables:
                keep = _keep(table)
                rows[table.name] = _copy_rows(source, dest, table, keep)
        out.dispose()
        with tmp.open("rb+") as written:
            os.fsync(written.fileno())
        tmp.replace(path)
        _fsync_folder(path.parent)
    finally:
        out.dispose()
        tmp.unlink(missing_ok=True)
    return Snapshot(path, SCHEMA_VERSION, made, rows)


def _keep(table: sa.Table) -> Any:
    """Which rows of ``table`` a backup keeps (a WHERE clause), None for all."""
    if table.name == derived.name:
        return table.c.name.in_(sorted(KEPT_DERIVED))
    return None


@contextlib.contextmanager
def _read_one_moment(url: str) -> Iterator[Connection]:
    """A connection whose reads all see the database at one moment, writers going on."""
    engine = sa.create_engine(url, poolclass=NullPool)
    if engine.dialect.name == "sqlite":
        # pysqlite begins a transaction only before a write; begin one before the first
        # read, so every read of this connection is of the same WAL snapshot.
        @sa.event.listens_for(engine, "connect")
        def _own_transactions(dbapi_connection: Any, _record: Any) -> None:
            dbapi_connection.isolation_level = None
            dbapi_connection.execute("PRAGMA busy_timeout = 30000")

        @sa.event.listens_for(engine, "begin")
        def _begin(connection: Connection) -> None:
            connection.exec_driver_sql("BEGIN")

        options: dict[str, Any] = {}
    else:
        options = {"isolation_level": "REPEATABLE READ", "postgresql_readonly": True}
    try:
        with engine.connect() as connection:
            db = connection.execution_options(**options)
            with db.begin():
                yield db
    finally:
        engine.dispose()


def _copy_rows(source: Connection, dest: Connection, table: sa.Table, where: Any = None) -> int:
    """Copy ``table``'s rows (those ``where`` keeps), in the order of their key; how many.

    JSON columns are read as their text, so a JSON ``null`` stays one and SQL NULL stays
    NULL (both would read back as None).
    """
    json_columns = [c.name for c in table.columns if isinstance(c.type, sa.JSON)]
    columns = [
        sa.cast(c, sa.Text).label(c.name) if c.name in json_columns else c for c in table.columns
    ]
    query = sa.select(*columns).order_by(*table.primary_key.columns)
    if where is not None:
        query = query.where(where)
    count = 0
    result = source.execution_options(yield_per=BATCH).execute(query)
    for part in result.partitions(BATCH):
        rows = [row._asdict() for row in part]
        for row in rows:
            for name in json_columns:
                row[name] = _json_value(row[name])
        dest.execute(sa.insert(table), rows)
        count += len(part)
    return count


def _json_value(text: str | None) -> Any:
    """A JSON column's text as the value to insert: SQL NULL, JSON null, or the value."""
    if text is None:
        return None  # none_as_null: SQL NULL
    value = json.loads(text)
    return sa.JSON.NULL if value is None else value


def _shown(url: str) -> str:
    """A database URL as a message may show it: without its password or query values."""
    try:
        return mask_url(sa.make_url(url).render_as_string(hide_password=True))
    except sa.exc.ArgumentError:
        return mask_url(url)


# -- blobs -----------------------------------------------------------------------------------


@dataclass(frozen=True)
class NamedBlob:
    """A blob that rows of the index name, and its size where the index knows it."""

    digest: str
    size: int | None


def named_blobs(db: Connection) -> Iterator[NamedBlob]:
    """Each blob the index on ``db`` names (records, logs, kept derived artifacts), once,
    in the order of their digests."""
    c, d = trials.c, derived.c
    named = sa.union_all(
        sa.select(c.mcap.label("digest"), c.mcap_size.label("size")),
        sa.select(c.stdout.label("digest"), sa.null().label("size")),
        sa.select(c.stderr.label("digest"), sa.null().label("size")),
        sa.select(d.digest.label("digest"), d.size.label("size")),
    ).subquery()
    query = (
        sa.select(named.c.digest, sa.func.max(named.c.size))
        .where(named.c.digest.is_not(None))
        .group_by(named.c.digest)
        .order_by(named.c.digest)
    )
    for digest, size in db.execute(query):
        yield NamedBlob(digest, None if size is None else int(size))


def count_named(db: Connection) -> int:
    c, d = trials.c, derived.c
    named = sa.union(
        sa.select(c.mcap.label("digest")),
        sa.select(c.stdout.label("digest")),
        sa.select(c.stderr.label("digest")),
        sa.select(d.digest.label("digest")),
    ).subquery()
    query = sa.select(sa.func.count()).select_from(named).where(named.c.digest.is_not(None))
    return int(db.execute(query).scalar_one())


def owner(db: Connection, digest: str) -> str:
    """What names the blob ``digest`` in the index, in words (for an error message)."""
    c = trials.c
    for column, what in ((c.mcap, "record"), (c.stdout, "stdout"), (c.stderr, "stderr")):
        found = db.execute(sa.select(c.id).where(column == digest).limit(1)).scalar()
        if found is not None:
            return f"trial {found}'s {what}"
    row = db.execute(
        sa.select(derived.c.trial_id, derived.c.name).where(derived.c.digest == digest).limit(1)
    ).first()
    return f"trial {row[0]}'s {row[1]}" if row is not None else "no row"


@dataclass
class BlobCopy:
    """What ``copy_blobs`` did."""

    copied: int = 0  # blobs written to the destination
    present: int = 0  # already there: not copied again
    bytes: int = 0  # copied
    total_bytes: int = 0  # of every blob named (on an object store: where the index knows)
    unreadable: dict[str, str] = field(default_factory=dict)  # digest -> why

    @property
    def blobs(self) -> int:
        return self.copied + self.present + len(self.unreadable)


class _SourceFailed(Exception):
    """Reading the source failed (wraps its error, so a write error is told apart)."""

    def __init__(self, error: Exception) -> None:
        self.error = error
        super().__init__(str(error))


class _Chunks:
    """A blob's checked chunks as the readable stream ``BlobStore.put_stream`` takes."""

    def __init__(self, chunks: Iterator[bytes]) -> None:
        self._chunks = chunks
        self.read_bytes = 0

    def read(self, _size: int = -1) -> bytes:
        try:
            chunk = next(self._chunks, b"")
        except (ArchiveError, OSError) as err:
            raise _SourceFailed(err) from err
        self.read_bytes += len(chunk)
        return chunk


def copy_blobs(
    blobs: Iterator[NamedBlob],
    total: int,
    source: BlobStore,
    dest: BlobStore,
    progress: Progress | None = None,
) -> BlobCopy:
    """Copy each of ``blobs`` from ``source`` into ``dest`` unless ``dest`` has it (of the
    size the index knows); each checked against its digest on the way.

    A blob the source lacks or holds damaged is noted in ``unreadable`` and the copy goes
    on; writing that fails (a full disk) stops it: an OSError naming ``dest``.
    """
    done = BlobCopy()
    for n, blob in enumerate(blobs, 1):
        held = _held(dest, blob)
        if held is not None:
            done.present += 1
            done.total_bytes += held
        else:
            stream = _Chunks(source.iter_chunks(blob.digest, CHUNK_SIZE))
            try:
                dest.put_stream(stream)  # type: ignore[arg-type]
            except _SourceFailed as failed:
                done.unreadable[blob.digest] = _why(failed.error)
            except OSError as err:  # writing: a full disk, say
                raise OSError(err.errno, err.strerror or str(err), dest.url) from None
            else:
                done.copied += 1
                done.bytes += stream.read_bytes
                done.total_bytes += stream.read_bytes
        if progress is not None:
            progress(n, total, done.bytes)
    return done


def _held(store: BlobStore, blob: NamedBlob) -> int | None:
    """The size of the store's copy of ``blob``; None if it has none (or, on a local
    disk, one of another size than the index knows: a copy to make again)."""
    if not store.local:
        return (blob.size or 0) if store.exists(blob.digest) else None
    try:
        size = os.path.getsize(store.path(blob.digest))
    except FileNotFoundError:
        return None
    return size if blob.size is None or size == blob.size else None


def _why(error: Exception) -> str:
    if isinstance(error, BlobNotFound):
        return "missing from the store"
    if isinstance(error, BlobCorrupt):
        return f"damaged (its bytes hash to {error.actual})"
    if isinstance(error, OSError):
        return error.strerror or str(error)
    return str(error)


# -- restoring -------------------------------------------------------------------------------


def rows_held(engine: Engine) -> dict[str, int]:
    """The rows each table of the index on ``engine`` holds (labd_meta aside); tables
    that are not there count none."""
    held = {}
    with engine.connect() as db:
        present = set(sa.inspect(db).get_table_names())
        for table in TABLES.sorted_tables:
            if table.name in present and table.name != meta.name:
                count = db.execute(sa.select(sa.func.count()).select_from(table)).scalar_one()
                if count:
                    held[table.name] = int(count)
    return held


def check_empty(engine: Engine) -> None:
    """TargetNotEmpty if the index on ``engine`` holds any row (of trials, or any other)."""
    held = rows_held(engine)
    if held:
        if trials.name in held:
            holds = f"{held[trials.name]} trial(s)"
        else:
            holds = "rows of " + ", ".join(f"{name} ({n})" for name, n in sorted(held.items()))
        raise TargetNotEmpty(f"the index at {_shown(str(engine.url))}", holds)


def restore_index(index: Path, engine: Engine) -> dict[str, int]:
    """Put every row of the backup's ``index`` (this labd's schema) into the empty index
    on ``engine``, made if need be, in one transaction; the rows per table."""
    found = schema_of(engine)
    if found is not None and found > SCHEMA_VERSION:
        raise BackupError(
            f"the index at {_shown(str(engine.url))} has schema {found}, newer than this"
            f" labd's {SCHEMA_VERSION}"
        )
    check_empty(engine)
    upgrade(engine)  # makes the tables (an empty database), or brings an empty one up
    source = sa.create_engine(sqlite_url(index), poolclass=NullPool)
    rows: dict[str, int] = {}
    try:
        with source.connect() as src, engine.begin() as dest:
            _take_meta(src, dest)
            for table in TABLES.sorted_tables:
                if table.name != meta.name:
                    rows[table.name] = _copy_rows(src, dest, table)
            if dest.dialect.name == "postgresql":
                _move_sequences(dest)
    finally:
        source.dispose()
    return rows


def _take_meta(src: Connection, dest: Connection) -> None:
    """The backup's labd_meta rows the target lacks (its schema row is the target's)."""
    table = TABLES.tables[meta.name]
    have = {row[0] for row in dest.execute(sa.select(table.c.key))}
    for key, value in src.execute(sa.select(table.c.key, table.c.value)):
        if key not in have:
            dest.execute(sa.insert(table).values(key=key, value=value))


def _move_sequences(db: Connection) -> None:
    """Set each id sequence past the largest id restored, so new rows get new ids."""
    for table in TABLES.sorted_tables:
        keys = list(table.primary_key.columns)
        if len(keys) != 1 or not isinstance(keys[0].type, sa.Integer):
            continue
        if table.autoincrement_column is None:
            continue
        column = keys[0]
        largest = sa.select(sa.func.max(column)).scalar_subquery()
        sequence = sa.func.pg_get_serial_sequence(table.name, column.name)
        db.execute(sa.select(sa.func.setval(sequence, sa.func.coalesce(largest, 0) + 1, False)))


@contextlib.contextmanager
def index_connection(index: Path) -> Iterator[Connection]:
    """A connection to a backup's index file (SQLite), for ``named_blobs`` and ``owner``."""
    engine = sa.create_engine(sqlite_url(index), poolclass=NullPool)
    try:
        with engine.connect() as db:
            yield db
    finally:
        engine.dispose()
