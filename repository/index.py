"""The index of the archive: trial records and users, in SQLAlchemy.

SQLite by default (a file under the lab's data folder), PostgreSQL for more than one
machine: the same tables and queries on both. A trial's row is its whole record:
what was asked (repository, ref, the commit it resolved to, task, parameters, seed,
submitter), where it is in the queue (status, lease), and what came out (manifest,
digests, metrics, the blobs of its MCAP and logs, whether a rerun reproduced).

The queue's rules (claiming, leases, quotas) live in ``scheduler.queue``; this module
keeps the rows and answers the archive's questions: trials by repository, commit,
task, status, user and time, newest first, a page at a time; and per commit, its trials
with their reruns.
"""

from __future__ import annotations

import hashlib
import math
import os
import re
import secrets
import time
from collections.abc import Collection, Iterator, Mapping, Sequence
from contextlib import contextmanager, suppress
from dataclasses import dataclass
from enum import StrEnum
from pathlib import Path
from typing import Any

import sqlalchemy as sa
from sqlalchemy.engine import Connection, Engine

from repository.errors import (
    ArchiveError,
    HeldOut,
    IndexUnreachable,
    RecordNotFound,
    SchemaMismatch,
)
from repository.masking import mask_url
from repository.tables import (
    derived,
    episodes,
    evaluations,
    meta,
    metadata,
    tokens,
    trials,
    users,
)
from repository.trial import Kind, Order, Outcome, Status, Trial
from repository.units import moment
from repository.wal import IndexFiles
from repository.well_known import REPLAY

SCHEMA_VERSION = 5  # 1: labd 0.1 (status succeeded/failed); 2: status and outcome apart;
# 3: trials say whether an error was the lab's fault (lab_fault); 4: matches, and a
# match leg's away team on its trial; 5: identities (people an OpenID provider vouches for)
# A user name: ASCII letters and digits, then also '.', '-' or '_' (so never ".", ".."
# or a name that looks like another in other scripts); unique without case.
NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,63}", re.ASCII)
HEX = frozenset("0123456789abcdef")


@dataclass(frozen=True)
class UserLimits:
    """What a new user may do unless the operator says otherwise."""

    max_running: int = 2  # trials running at once
    max_daily: int = 500  # trials submitted per 24 hours


USER_LIMITS = UserLimits()


@dataclass(frozen=True)
class User:
    name: str
    max_running: int
    max_daily: int
    created: float
    worker: bool = False


@dataclass(frozen=True)
class Page:
    """One page of a list, newest first; ``next`` is the cursor of the following page."""

    items: list[Trial]
    next: int | None


class Sort(StrEnum):
    """How ``Index.find`` sorts trials: newest first, or best reward first."""

    TIME = "time"
    REWARD = "reward"


@dataclass(frozen=True)
class Derived:
    """A derived artifact of a trial's record: a blob of the store, and what it is."""

    name: str
    digest: str
    size: int
    media_type: str


@dataclass(frozen=True)
class CommitPage:
    """A commit's trials: originals newest first, their reruns, and the verdicts' counts."""

    commit: str
    repositories: list[str]
    trials: list[Trial]
    reruns: dict[int, list[Trial]]  # by the id of the trial they rerun
    rerun_counts: dict[str, int]  # reproduced, diverged, pending
    truncated: bool


@dataclass(frozen=True)
class Filters:
    repository: str | None = None
    commit: str | None = None  # a full commit or a prefix of at least 4 hex digits
    task: str | None = None
    status: Status | None = None
    outcome: Outcome | None = None
    kind: Kind | None = None
    submitter: str | None = None
    since: float | None = None  # created at or after (epoch seconds)
    until: float | None = None  # created before
    rerun_of: int | None = None
    public: bool | None = None
    has_record: bool | None = None  # with an MCAP record (True) or without (False)
    held_out: bool = False  # also the episodes of held-out suites (the operator's)


def connect(url: str, **engine_options: Any) -> Engine:
    """An engine for ``url`` (``sqlite:///path`` or ``postgresql+psycopg://...``)."""
    if url.startswith("sqlite"):
        private_file(sa.make_url(url).database)
        engine = sa.create_engine(url, connect_args={"timeout": 30}, **engine_options)
        sa.event.listen(engine, "connect", _sqlite_pragmas)
        return engine
    return sa.create_engine(url, pool_pre_ping=True, **engine_options)


def private_file(path: str | None) -> None:
    """Make the SQLite file at ``path`` empty and readable by its owner only (0600) if
    there is none yet: SQLite would make it 0644, and it holds password and token hashes
    and held-out seeds; its WAL and shared-memory files take the file's mode."""
    if not path or path == ":memory:" or path.startswith("file:"):
        return
    with suppress(OSError):  # there already, or no folder: SQLite says which
        os.close(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_CLOEXEC, 0o600))


def _sqlite_pragmas(dbapi_connection: Any, _record: Any) -> None:
    # WAL lets readers (the API) go on while a worker writes; foreign keys are off by default.
    cursor = dbapi_connection.cursor()
    cursor.execute("PRAGMA journal_mode=WAL")
    cursor.execute("PRAGMA synchronous=NORMAL")
    cursor.execute("PRAGMA foreign_keys=ON")
    cursor.close()


def _sqlite_writer(url: sa.URL) -> Engine:
    """An engine whose transactions start with BEGIN IMMEDIATE.

    A transaction that reads and then writes (check a quota, then insert) would otherwise
    start as a reader and fail at once with "database is locked" when another connection
    wrote in between; taking the write lock first makes writers queue for it instead.
    """
    engine = sa.create_engine(url, connect_args={"timeout": 30})
    sa.event.listen(engine, "connect", _sqlite_pragmas)

    @sa.event.listens_for(engine, "connect")
    def _no_implicit_begin(dbapi_connection: Any, _record: Any) -> None:
        dbapi_connection.isolation_level = None

    @sa.event.listens_for(engine, "begin")
    def _begin_immediate(connection: Connection) -> None:
        connection.exec_driver_sql("BEGIN IMMEDIATE")

    return engine


class Index:
    """The archive's tables on one database; safe to share between threads."""

    def __init__(self, engine: Engine, *, clock: Any = time.time) -> None:
        self.engine = engine  # reads
        sqlite = engine.dialect.name == "sqlite"
        self.writer = _sqlite_writer(engine.url) if sqlite else engine  # transactions
        self.clock = clock
        self.trials = trials
        self.users = users
        self.tokens = tokens
        self.files: IndexFiles | None = None  # a SQLite file's, watched once created

    @classmethod
    def open(cls, url: str, *, clock: Any = time.time, **engine_options: Any) -> Index:
        index = cls(connect(url, **engine_options), clock=clock)
        try:
            index.create()
        except sa.exc.OperationalError as err:
            index.close()
            where = mask_url(index.engine.url.render_as_string(hide_password=True))
            reason = str(err.orig or err).strip().splitlines()[0]
            raise IndexUnreachable(where, reason) from None
        except BaseException:
            index.close()
            raise
        return index

    def create(self) -> None:
        """Create the tables if they are missing; refuse a database of another schema.

        An index of an older schema is upgraded by ``repository.migrate`` (``labd
        migrate``), never silently here: the operator decides when to change it.
        """
        with self.begin() as db:
            existing = sa.inspect(db).has_table(meta.name)
            found = (
                db.execute(sa.select(meta.c.value).where(meta.c.key == "schema")).scalar()
                if existing
                else None
            )
        if found is not None and found != str(SCHEMA_VERSION):
            raise SchemaMismatch(int(found), SCHEMA_VERSION)
        metadata.create_all(self.engine)
        with self.begin() as db:
            found = db.execute(sa.select(meta.c.value).where(meta.c.key == "schema")).scalar()
            if found is None:
                db.execute(sa.insert(meta).values(key="schema", value=str(SCHEMA_VERSION)))
        database = self.engine.url.database
        if self.engine.dialect.name == "sqlite" and database and database != ":memory:":
            self.files = self.files or IndexFiles(Path(database))

    def close(self) -> None:
        if self.files is not None:
            self.files.close()
        self.engine.dispose()
        self.writer.dispose()

    def check(self) -> None:
        """Raise ``IndexLost`` if the index's files are no longer the ones it opened
        (``repository.wal``); writes are refused from then on."""
        if self.files is not None:
            self.files.check()

    @contextmanager
    def begin(self) -> Iterator[Connection]:
        """A transaction that may read and then write (never on files that changed
        under the lab: ``check``)."""
        self.check()
        with self.writer.begin() as db:
            yield db

    # -- users --------------------------------------------------------------------------

    def add_user(
        self,
        name: str,
        *,
        max_running: int = USER_LIMITS.max_running,
        max_daily: int = USER_LIMITS.max_daily,
        worker: bool = False,
        token: bool = True,
    ) -> str:
        """Add a user and return their new token (only its hash is kept).

        Without ``token`` (a person who signed up on the pages) the user has no token
        yet, and "" is returned: they make their own on the tokens page.
        """
        check_name(name)
        secret = "labd_" + secrets.token_urlsafe(24)
        now = self.clock()
        with self.begin() as db:
            lock_users(db)
            if db.execute(sa.select(users.c.name).where(users.c.name == name)).first():
                raise ArchiveError(f"user {name!r} exists already; choose another name")
            same = db.execute(
                sa.select(users.c.name).where(sa.func.lower(users.c.name) == name.lower())
            ).scalar()
            if same is not None:
                raise ArchiveError(
                    f"user name {name!r} is taken: names are told apart without case, and"
                    f" {same!r} exists; choose another name"
                )
            db.execute(
                sa.insert(users).values(
                    name=name,
                    # never given out when ``token`` is false: nobody can present it
                    token_sha256=token_hash(secret),
                    created=now,
                    max_running=max_running,
                    max_daily=max_daily,
                    worker=worker,
                )
            )
            if token:
                db.execute(
                    sa.insert(tokens).values(
                        user=name,
                        sha256=token_hash(secret),
                        label="made by the operator (labd users add)",
                        created=now,
                    )
                )
        return secret if token else ""

    def user_by_token(self, token: str) -> User | None:
        """The user a token belongs to; None if it is unknown or revoked."""
        digest = token_hash(token)
        with self.engine.connect() as db:
            found = db.execute(
                sa.select(tokens.c.user, tokens.c.revoked).where(tokens.c.sha256 == digest)
            ).first()
            if found is not None:
                if found.revoked is not None:
                    return None
                row = db.execute(sa.select(users).where(users.c.name == found.user)).first()
                return None if row is None else _user(row)
            # A token an older labd made, kept only in users (until its owner has others).
            row = db.execute(sa.select(users).where(users.c.token_sha256 == digest)).first()
            if row is None:
                return None
            mine = db.execute(sa.select(tokens.c.id).where(tokens.c.user == row.name)).first()
        return _user(row) if mine is None else None

    def name_collisions(self) -> list[list[str]]:
        """Users whose names are the same without case (made by a labd before names were
        told apart without case): each group, by name. They keep working as they are;
        no new name may join them."""
        folded = sa.func.lower(users.c.name)
        with self.engine.connect() as db:
            shared = sa.select(folded).group_by(folded).having(sa.func.count() > 1)
            rows = db.execute(
                sa.select(users.c.name).where(folded.in_(shared)).order_by(folded, users.c.name)
            ).all()
        groups: dict[str, list[str]] = {}
        for (name,) in rows:
            groups.setdefault(name.lower(), []).append(name)
        return list(groups.values())

    def users_list(self) -> list[User]:
        """Every user, by name."""
        with self.engine.connect() as db:
            rows = db.execute(sa.select(users).order_by(users.c.name)).all()
        return [_user(r) for r in rows]

    def user(self, name: str) -> User:
        with self.engine.connect() as db:
            row = db.execute(sa.select(users).where(users.c.name == name)).first()
        if row is None:
            raise RecordNotFound("user", name)
        return _user(row)

    # -- trials -------------------------------------------------------------------------

    def add_trial(self, order: Order, *, submitter: str, db: Connection | None = None) -> int:
        """Queue ``order`` for ``submitter`` as a new trial (in ``db``'s transaction, if
        given); its id. Its task is resolved by then (``Order``)."""
        if order.task is None:
            raise ArchiveError("a trial is queued with its task resolved; this order names none")
        values = {
            "kind": order.kind.value,
            "repository": order.repository,
            "ref": order.ref,
            "commit": order.commit,
            "task": order.task,
            "params": dict(order.params),
            "seed": order.seed,
            "submitter": submitter,
            "public": order.public,
            "rerun_of": order.rerun_of,
            "data": [p.model_dump(mode="json") for p in order.data] if order.data else None,
            "away_repository": order.away.repository if order.away else None,
            "away_ref": order.away.ref if order.away else None,
            "away_commit": order.away.commit if order.away else None,
            "step_deadline": order.step_deadline,
            "status": Status.QUEUED.value,
            "reason": "waiting for a worker",
            "created": self.clock(),
            "attempts": 0,
            "cancel_requested": False,
        }
        if db is not None:
            return _inserted_id(db.execute(sa.insert(trials).values(values)))
        with self.begin() as own:
            return _inserted_id(own.execute(sa.insert(trials).values(values)))

    def blob_readable(self, digest: str, worker: str | None = None) -> bool:
        """Whether a blob may be served: it is the record, a log or a derived artifact of
        a trial anyone may read (not a hidden held-out episode), or, for the worker
        account ``worker``, what a trial it holds needs (its pinned records, its rerun
        original's record). A blob no trial holds (an upload not yet filed, a guess) is
        nobody's to read."""
        t = trials.c
        held = sa.or_(t.mcap == digest, t.stdout == digest, t.stderr == digest)
        with self.engine.connect() as db:
            public = db.execute(
                sa.select(
                    sa.or_(
                        sa.exists().where(held, ~hidden(t.id)),
                        sa.exists().where(derived.c.digest == digest, ~hidden(derived.c.trial_id)),
                    )
                )
            ).scalar()
            if public or worker is None:
                return bool(public)
            held_by = db.execute(
                sa.select(t.data, t.rerun_of).where(
                    t.status == Status.RUNNING.value,
                    t.worker.startswith(f"{worker}@", autoescape=True),
                )
            ).all()
            if any(digest == r.get("mcap") for row in held_by for r in row.data or ()):
                return True
            originals = [row.rerun_of for row in held_by if row.rerun_of is not None]
            return bool(originals) and bool(
                db.execute(sa.select(sa.exists().where(t.id.in_(originals), held))).scalar()
            )

    def is_hidden(self, trial_id: int) -> bool:
        """Whether the trial is an episode of a held-out suite not yet retired."""
        with self.engine.connect() as db:
            return bool(db.execute(sa.select(hidden(sa.literal(trial_id)))).scalar())

    def readable(self, trial_id: int) -> Trial:
        """A trial anyone may read: ``HeldOut`` if it is an episode of a held-out suite
        not yet retired (``trial`` is the lab's own read, which sees every trial)."""
        with self.engine.connect() as db:
            if db.execute(sa.select(hidden(sa.literal(trial_id)))).scalar():
                raise HeldOut(trial_id)
        return self.trial(trial_id)

    def trial(self, trial_id: int) -> Trial:
        with self.engine.connect() as db:
            row = db.execute(sa.select(trials).where(trials.c.id == trial_id)).first()
        if row is None:
            raise RecordNotFound("trial", str(trial_id))
        return to_trial(row)

    def find(
        self,
        filters: Filters,
        *,
        limit: int = 50,
        before: int | None = None,
        order: Sort = Sort.TIME,
        offset: int = 0,
    ) -> Page:
        """Trials matching ``filters``, a page at a time.

        By ``time``, newest first, and ``before`` is a page's cursor (the id to go below);
        by ``reward``, best first (trials without one last), a page at ``offset``.
        """
        query = sa.select(trials).where(*self._conditions(filters))
        if order is Sort.REWARD:
            query = query.order_by(trials.c.reward.desc().nulls_last(), trials.c.id.desc())
            query = query.offset(offset)
        else:
            if before is not None:
                query = query.where(trials.c.id < before)
            query = query.order_by(trials.c.id.desc())
        query = query.limit(limit + 1)
        with self.engine.connect() as db:
            rows = [to_trial(r) for r in db.execute(query)]
        more = len(rows) > limit
        rows = rows[:limit]
        return Page(rows, rows[-1].id if more and rows else None)

    def _conditions(self, f: Filters) -> list[sa.ColumnElement[bool]]:
        c = trials.c
        conditions: list[sa.ColumnElement[bool]] = []
        if f.repository is not None:
            conditions.append(c.repository.in_(spellings(f.repository)))
        if f.commit is not None:
            conditions.append(played_by(f.commit))
        if f.task is not None:
            conditions.append(c.task == f.task)
        if f.status is not None:
            conditions.append(c.status == Status(f.status).value)
        if f.outcome is not None:
            conditions.append(c.outcome == Outcome(f.outcome).value)
        if f.kind is not None:
            conditions.append(c.kind == Kind(f.kind).value)
        if f.submitter is not None:
            conditions.append(c.submitter == f.submitter)
        if f.since is not None:
            conditions.append(c.created >= f.since)
        if f.until is not None:
            conditions.append(c.created < f.until)
        if f.rerun_of is not None:
            conditions.append(c.rerun_of == f.rerun_of)
        if f.public is not None:
            conditions.append(c.public == f.public)
        if f.has_record is not None:
            conditions.append(c.mcap.is_not(None) if f.has_record else c.mcap.is_(None))
        if not f.held_out:
            conditions.append(~hidden(c.id))
        return conditions

    def commits(self, prefix: str) -> list[str]:
        """The full commits that start with ``prefix`` (at most a few)."""
        own = sa.select(trials.c.commit.label("commit")).where(commit_condition(prefix))
        away = sa.select(trials.c.away_commit.label("commit")).where(
            commit_condition(prefix, trials.c.away_commit)
        )
        query = sa.select(sa.union(own, away).subquery().c.commit).limit(10)
        with self.engine.connect() as db:
            return sorted(r[0] for r in db.execute(query))

    def commit_page(self, commit: str, *, limit: int = 200) -> CommitPage:
        """A commit's trials, newest first, each original with its reruns.

        ``reproduced``/``diverged``/``pending`` count the reruns of this commit that
        ended with an identical data digest, with another one, or have not ended.
        """
        found = self.commits(commit)
        if not found:
            raise RecordNotFound("commit with trials", commit)
        if len(found) > 1:
            raise ArchiveError(
                f"commit {commit!r} is ambiguous: it starts {', '.join(c[:12] for c in found)}"
            )
        full = found[0]
        query = (
            sa.select(trials)
            .where(played_by(full), ~hidden(trials.c.id))
            .order_by(trials.c.id.desc())
            .limit(limit + 1)
        )
        with self.engine.connect() as db:
            rows = [to_trial(r) for r in db.execute(query)]
        truncated = len(rows) > limit
        rows = rows[:limit]
        reruns: dict[int, list[Trial]] = {}
        originals = []
        counts = {"reproduced": 0, "diverged": 0, "pending": 0}
        for row in rows:
            if row.rerun_of is None:
                originals.append(row)
                continue
            reruns.setdefault(row.rerun_of, []).append(row)
            if row.reproduced is True:
                counts["reproduced"] += 1
            elif row.reproduced is False:
                counts["diverged"] += 1
            else:
                counts["pending"] += 1
        return CommitPage(
            commit=full,
            repositories=sorted(
                {r.repository for r in rows if r.commit == full}
                | {r.away_repository for r in rows if r.away_commit == full and r.away_repository}
            ),
            trials=originals,
            reruns=reruns,
            rerun_counts=counts,
            truncated=truncated,
        )

    def update(self, trial_id: int, db: Connection | None = None, **values: Any) -> int:
        """Set columns of one trial; the number of rows changed."""
        statement = sa.update(trials).where(trials.c.id == trial_id).values(values)
        if db is not None:
            return int(db.execute(statement).rowcount)
        with self.begin() as own:
            return int(own.execute(statement).rowcount)

    def put_derived(self, trial_id: int, item: Derived) -> None:
        """Keep ``item`` as the trial's artifact of that name (replacing an older one)."""
        with self.begin() as db:
            db.execute(
                sa.delete(derived).where(
                    derived.c.trial_id == trial_id, derived.c.name == item.name
                )
            )
            db.execute(
                sa.insert(derived).values(
                    trial_id=trial_id,
                    name=item.name,
                    digest=item.digest,
                    size=item.size,
                    media_type=item.media_type,
                    created=self.clock(),
                )
            )

    def derived(self, trial_id: int) -> dict[str, Derived]:
        """The trial's derived artifacts, by name."""
        with self.engine.connect() as db:
            rows = db.execute(sa.select(derived).where(derived.c.trial_id == trial_id)).all()
        return {r.name: Derived(r.name, r.digest, r.size, r.media_type) for r in rows}

    def unrendered(self, name: str, skip: Collection[int] = ()) -> int | None:
        """The newest trial with a record and a replay verdict but no derived artifact
        ``name`` (a video not yet rendered), leaving out ``skip``; None if there is none."""
        made = sa.select(derived.c.trial_id).where(derived.c.name == name)
        replayed = sa.select(derived.c.trial_id).where(derived.c.name == REPLAY)
        query = (
            sa.select(trials.c.id)
            .where(
                trials.c.mcap.is_not(None),
                trials.c.id.in_(replayed),
                trials.c.id.not_in(made),
            )
            .order_by(trials.c.id.desc())
            .limit(1)
        )
        if skip:
            query = query.where(trials.c.id.not_in(list(skip)))
        with self.engine.connect() as db:
            found = db.execute(query).scalar()
        return None if found is None else int(found)

    def unreplayed(self, trusted: Sequence[str], skip: Collection[int] = ()) -> int | None:
        """The oldest finished trial with a record but no replay verdict, run by a worker
        whose name starts with none of ``trusted`` (the lab's own, which replay what they
        file themselves), leaving out ``skip``; None if there is none."""
        replayed = sa.select(derived.c.trial_id).where(derived.c.name == REPLAY)
        t = trials.c
        query = (
            sa.select(t.id)
            .where(
                t.status == Status.FINISHED.value,
                t.mcap.is_not(None),
                t.worker.is_not(None),
                *(~t.worker.startswith(prefix, autoescape=True) for prefix in trusted),
                t.id.not_in(replayed),
            )
            .order_by(t.id)
            .limit(1)
        )
        if skip:
            query = query.where(t.id.not_in(list(skip)))
        with self.engine.connect() as db:
            found = db.execute(query).scalar()
        return None if found is None else int(found)

    def bulk_insert(self, rows: Sequence[Mapping[str, Any]]) -> None:
        """Insert finished records as they are (benchmarks, imports)."""
        with self.begin() as db:
            db.execute(sa.insert(trials), [dict(r) for r in rows])


def reward_of(metrics: Mapping[str, Any] | None) -> float | None:
    """The reward metric of a trial, for the ``reward`` column (None if it has none)."""
    value = (metrics or {}).get("reward")
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    return float(value) if math.isfinite(value) else None


def spellings(repository: str) -> list[str]:
    """The ways one repository's URL is written: with and without a trailing ``.git`` or
    ``/`` (``https://host/x``, ``https://host/x.git``), so the archive finds it by either."""
    base = repository.rstrip("/").removesuffix(".git")
    return sorted({repository, base, base + ".git"})


def commit_condition(
    commit: str, column: sa.ColumnElement[str] | None = None
) -> sa.ColumnElement[bool]:
    """Rows whose commit is ``commit`` or starts with it (an index range, on any database);
    of ``column`` if given (a match leg's away team's)."""
    commit = commit.lower()
    if not 4 <= len(commit) <= 40 or not set(commit) <= HEX:
        raise ArchiveError(f"commit {commit!r}: give 4 to 40 hexadecimal digits")
    of = trials.c.commit if column is None else column
    if len(commit) == 40:
        return of == commit
    return sa.and_(of >= commit, of < commit + "g")


def played_by(commit: str) -> sa.ColumnElement[bool]:
    """Trials of ``commit`` (or of the commits starting with it): its own, and the legs
    of matches it played away."""
    return sa.or_(commit_condition(commit), commit_condition(commit, trials.c.away_commit))


def hidden(trial_id: sa.ColumnElement[int]) -> sa.Exists:
    """Whether the trial is an episode of a held-out suite not yet retired."""
    return sa.exists().where(episodes.c.trial_id == trial_id, episodes.c.hidden)


def blind(trial_id: sa.ColumnElement[int]) -> sa.Exists:
    """Whether the trial is an episode of a held-out suite, retired or not: its
    controller runs blind (told no seed), and so does every rerun of it, so that the
    rerun's data can equal the original's."""
    held_out = sa.select(evaluations.c.id).where(evaluations.c.held_out)
    return sa.exists().where(
        episodes.c.trial_id == trial_id, episodes.c.evaluation_id.in_(held_out)
    )


def to_trial(row: Any) -> Trial:
    """A row of ``trials`` as the typed record (times become UTC datetimes)."""
    values = dict(row._mapping)
    for name in ("created", "started", "finished"):
        values[name] = None if values[name] is None else moment(values[name])
    values.pop("lease_until", None)
    values.pop("reward", None)  # the record's reward is its metrics'
    return Trial.model_validate(values)


def lock_users(db: sa.Connection) -> None:
    """Take the turn to add a user in this transaction: no two new names are checked
    against the taken ones at once (SQLite's writers already take turns)."""
    if db.dialect.name == "postgresql":
        db.execute(sa.text("SELECT pg_advisory_xact_lock(hashtext('labd:users'))"))


def check_name(name: str) -> None:
    """A user name the lab accepts for a new user (ArchiveError saying what is allowed
    if not): ASCII only, so that no name can pass for another (alice with a Cyrillic or
    a fullwidth a), and starting with a letter or digit (never '.' or '..')."""
    if NAME.fullmatch(name) is None:
        raise ArchiveError(
            f"user name {name!r}: use 1 to 64 ASCII letters, digits, '-', '_' or '.',"
            " starting with a letter or a digit"
        )


def token_hash(token: str) -> str:
    return hashlib.sha256(token.encode()).hexdigest()


def _user(row: Any) -> User:
    return User(row.name, row.max_running, row.max_daily, row.created, row.worker)


def _inserted_id(result: sa.CursorResult[Any]) -> int:
    key = result.inserted_primary_key
    assert key is not None
    return int(key[0])
