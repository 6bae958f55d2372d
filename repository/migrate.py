"""Upgrading an archive's index in place, from an older schema to this labd's.

Schema 4 adds matches (the ``matches`` and ``match_legs`` tables) and, on each trial,
the away team of a match's leg and its step deadline (``away_repository``,
``away_ref``, ``away_commit``, ``step_deadline``; none for the trials filed before).

Schema 3 says of each trial whether its error was the lab's fault (``lab_fault``: its
worker lost, its storage failed), so that an evaluation with such an episode is partial
rather than scored as the controller's error; trials filed before say it was not.

Schema 2 also keeps the reward metric as a column (``reward``), to sort and rank by, and
the lab's signature of each record filed from then on (``signature``; records filed
before have none), and the archived records a trial learns from, pinned when it was
submitted (``data``; none before).

Schema 1 (labd 0.1) kept one ``status`` for both the lifecycle and the result:
``succeeded`` meant the trial ran to its end, whether or not the robot achieved its
task, and ``failed`` meant it broke. Schema 2 keeps them apart (``repository.trial``):
``status`` is ``finished`` and the ``outcome`` says ``success`` (the metrics say the
task was achieved), ``fail`` (it ran to its end without that) or ``error`` (the old
``failed``). Every row is kept; only these columns change, in one transaction, so an
interrupted upgrade leaves the old schema as it was.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any

import sqlalchemy as sa
from sqlalchemy.engine import Connection, Engine

from repository.errors import ArchiveError
from repository.index import SCHEMA_VERSION, reward_of
from repository.tables import meta, metadata, trials
from repository.trial import Outcome, Status

log = logging.getLogger("repository.migrate")


@dataclass
class Upgrade:
    """What an upgrade did: the schema before and after, and the rows it changed."""

    before: int
    after: int
    changed: dict[str, int] = field(default_factory=dict)  # "succeeded -> success": rows

    def __str__(self) -> str:
        if self.before == self.after:
            return f"the index already has schema {self.after}; nothing to do"
        counts = ", ".join(f"{n} {what}" for what, n in sorted(self.changed.items()))
        return f"upgraded the index from schema {self.before} to {self.after}" + (
            f": {counts}" if counts else ""
        )


def schema_of(engine: Engine) -> int | None:
    """The schema version an index says it has; None for an empty database."""
    with engine.connect() as db:
        if not sa.inspect(db).has_table(meta.name):
            return None
        found = db.execute(sa.select(meta.c.value).where(meta.c.key == "schema")).scalar()
    return None if found is None else int(found)


def upgrade(engine: Engine) -> Upgrade:
    """Bring the index on ``engine`` to this labd's schema, keeping every row."""
    found = schema_of(engine)
    if found is None:
        metadata.create_all(engine)
        with engine.begin() as db:
            db.execute(sa.insert(meta).values(key="schema", value=str(SCHEMA_VERSION)))
        return Upgrade(SCHEMA_VERSION, SCHEMA_VERSION)
    if found > SCHEMA_VERSION:
        raise ArchiveError(
            f"the index has schema {found}, newer than this labd's {SCHEMA_VERSION}; "
            "run the newer labd"
        )
    result = Upgrade(found, SCHEMA_VERSION)
    with engine.begin() as db:
        if found < 2:
            _from_1(db, result)
        if found < 3:
            _from_2(db)
        if found < 4:
            _from_3(db)
        # 4 → 5: the identities table, made with the indexes below
        db.execute(sa.update(meta).where(meta.c.key == "schema").values(value=str(SCHEMA_VERSION)))
    metadata.create_all(engine)  # indexes added since
    log.info("%s", result)
    return result


def _from_3(db: Connection) -> None:
    """Schema 3 → 4: a match leg's away team on its trial (none before); the match
    tables themselves are made with the indexes, below."""
    for column, kind in (
        ("away_repository", "VARCHAR(2048)"),
        ("away_ref", "VARCHAR(256)"),
        ("away_commit", "VARCHAR(40)"),
        ("step_deadline", "FLOAT"),
    ):
        db.execute(sa.text(f"ALTER TABLE trials ADD COLUMN {column} {kind}"))


def _from_2(db: Connection) -> None:
    """Schema 2 → 3: add ``lab_fault`` (false for every trial filed before)."""
    db.execute(sa.text("ALTER TABLE trials ADD COLUMN lab_fault BOOLEAN NOT NULL DEFAULT FALSE"))


def _from_1(db: Connection, result: Upgrade) -> None:
    """Schema 1 → 2: add ``kind`` and ``outcome``; split the old statuses."""
    db.execute(sa.text("ALTER TABLE trials ADD COLUMN kind VARCHAR(16) NOT NULL DEFAULT 'trial'"))
    db.execute(sa.text("ALTER TABLE trials ADD COLUMN outcome VARCHAR(16)"))
    db.execute(sa.text("ALTER TABLE trials ADD COLUMN reward FLOAT"))
    db.execute(sa.text("ALTER TABLE trials ADD COLUMN signature JSON"))
    db.execute(sa.text("ALTER TABLE trials ADD COLUMN data JSON"))
    c = trials.c
    rows = db.execute(
        sa.select(c.id, c.status, c.metrics).where(c.status.in_(("succeeded", "failed")))
    ).all()
    changes = []
    for trial_id, old, metrics in rows:
        outcome = _outcome(old, metrics)
        changes.append({"row": trial_id, "new": outcome.value})
        key = f"{old} -> {outcome.value}"
        result.changed[key] = result.changed.get(key, 0) + 1
    rewards = [
        {"row": trial_id, "new": reward}
        for trial_id, metrics in db.execute(
            sa.select(c.id, c.metrics).where(c.metrics.is_not(None))
        )
        if (reward := reward_of(metrics)) is not None
    ]
    if rewards:
        db.execute(
            sa.update(trials).where(c.id == sa.bindparam("row")).values(reward=sa.bindparam("new")),
            rewards,
        )
    if changes:
        db.execute(
            sa.update(trials)
            .where(c.id == sa.bindparam("row"))
            .values(status=Status.FINISHED.value, outcome=sa.bindparam("new")),
            changes,
        )


def _outcome(old: str, metrics: Any) -> Outcome:
    if old == "failed":
        return Outcome.ERROR
    achieved = isinstance(metrics, dict) and metrics.get("success") is True
    return Outcome.SUCCESS if achieved else Outcome.FAIL
