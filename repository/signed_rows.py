"""An index held to the lab's signatures: each signed row must say what its signature says.

The lab signs each record it files (``labd.record/2``: the trial, how it ended, its
digests, its metrics, when; ``repository.signing``) and each evaluation once its episodes
have ended, and keeps the signature in the row. A restore (``labd restore``) holds every
row of the backup's index to them before it puts one into a lab, so that an index edited
after the lab wrote it (an outcome made better, a digest changed) is refused rather than
served, whatever its manifest says:

- a trial row with a signature: the signature must check with the lab's public keys, and
  every field its statement names must have in the row the value the lab signed;
- a trial row without one that reads as a filed record (an outcome of ``success`` or
  ``fail``, or a record's digest): refused, unless it finished before the lab's first
  signed record (a lab older than signing filed it, unsigned, and nothing can vouch for
  it, in the lab or in its backup); a lab's own errors (a lease lost) and cancellations
  are never signed, and are taken as they are;
- an evaluation with a signature: it must check, name this evaluation and its commit and
  suite, and each episode it lists as finished must have the outcome it signed.

``check`` answers the problems in words, a few named and the rest counted.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from typing import Any

import sqlalchemy as sa
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PublicKey
from sqlalchemy.engine import Connection

from repository.digests import canonical_json
from repository.signing import RECORDS, Signature, SignatureError, verify
from repository.tables import evaluations, trials
from repository.units import moment

FILED = frozenset({"success", "fail"})  # outcomes only a filed (signed) record has
SAID = 3  # problems named in the message; the others are counted
BATCH = 1000
# an evaluation's fields a statement may name, checked against its row
EVALUATION_FIELDS = ("repository", "commit", "task", "task_version", "suite", "suite_version")

Keys = Mapping[str, Ed25519PublicKey | str]


def check(db: Connection, keys: Keys) -> list[str]:
    """Each row of the index on ``db`` that its signature does not bear out, in words
    (``trial 3: its outcome is 'success', the lab signed 'fail'``); empty if none."""
    first = _first_signed(db)
    problems = list(_trials(db, keys, first))
    problems += _evaluations(db, keys)
    return problems


def summary(problems: list[str]) -> str:
    """The problems as one line: the first few, and how many more."""
    more = len(problems) - SAID
    return "; ".join(problems[:SAID]) + (f"; and {more} more" if more > 0 else "")


def _first_signed(db: Connection) -> float | None:
    """When the first signed record was filed: rows finished before it may predate
    signing (an older labd's)."""
    c = trials.c
    found = db.execute(
        sa.select(sa.func.min(c.finished)).where(
            c.signature.is_not(None), sa.cast(c.signature, sa.Text) != "null"
        )
    ).scalar()
    return None if found is None else float(found)


def _trials(db: Connection, keys: Keys, first: float | None) -> Iterator[str]:
    result = db.execution_options(yield_per=BATCH).execute(sa.select(trials).order_by(trials.c.id))
    for row in result:
        if not row.signature:
            if (row.outcome in FILED or row.mcap is not None) and (
                first is not None and (row.finished is None or row.finished >= first)
            ):
                yield (
                    f"trial {row.id}: a filed record ({row.outcome}) without the lab's"
                    " signature, filed after the lab signed its records"
                )
            continue
        yield from _record(row, keys)


def _record(row: Any, keys: Keys) -> Iterator[str]:
    """What is wrong with a signed trial row, if anything."""
    try:
        signature = Signature.from_json(row.signature)
        verify(signature, keys)
    except SignatureError as err:
        yield f"trial {row.id}: its signature does not check ({err})"
        return
    said = signature.statement
    if said.get("schema") not in RECORDS:
        yield f"trial {row.id}: its signature is of a {said.get('schema')!r}, not a record"
        return
    for name, signed in sorted(said.items()):
        if name in ("schema", "key"):
            continue
        held = _held(row, name)
        if held is _MISSING:
            yield f"trial {row.id}: the lab signed its {name}, which the index has no column for"
        elif canonical_json(held) != canonical_json(signed):
            yield f"trial {row.id}: its {name} is {held!r}, the lab signed {signed!r}"


_MISSING = object()


def _held(row: Any, name: str) -> Any:
    """The value the row holds for a statement's field ``name``, as the lab signs it."""
    if name == "trial":
        return row.id
    if name == "finished":
        return None if row.finished is None else moment(row.finished).isoformat()
    return row._mapping.get(name, _MISSING)


def _evaluations(db: Connection, keys: Keys) -> list[str]:
    problems = []
    outcomes = {}  # trial id -> outcome, read once for all evaluations
    signed = db.execute(
        sa.select(evaluations)
        .where(evaluations.c.signature.is_not(None))
        .order_by(evaluations.c.id)
    ).all()
    for row in signed:
        if not row.signature:  # {}: a lab without keys ended it
            continue
        try:
            signature = Signature.from_json(row.signature)
            verify(signature, keys)
        except SignatureError as err:
            problems.append(f"evaluation {row.id}: its signature does not check ({err})")
            continue
        said = signature.statement
        if said.get("evaluation") != row.id:
            problems.append(
                f"evaluation {row.id}: its signature is evaluation {said.get('evaluation')}'s"
            )
            continue
        for name in EVALUATION_FIELDS:
            if name in said and canonical_json(said[name]) != canonical_json(getattr(row, name)):
                held = getattr(row, name)
                problems.append(
                    f"evaluation {row.id}: its {name} is {held!r}, the lab signed {said[name]!r}"
                )
        for episode in _episodes(said):
            trial = episode["trial"]
            if trial not in outcomes:
                outcomes[trial] = db.execute(
                    sa.select(trials.c.outcome).where(trials.c.id == trial)
                ).scalar()
            if episode.get("status") == "finished" and outcomes[trial] != episode.get("outcome"):
                problems.append(
                    f"evaluation {row.id}: its episode trial {trial} has the outcome"
                    f" {outcomes[trial]!r}, the lab signed {episode.get('outcome')!r}"
                )
    return problems


def _episodes(said: Mapping[str, Any]) -> Iterator[Mapping[str, Any]]:
    """The episodes a statement lists (under ``rows`` or ``episodes``, as versions of it
    have), each with its trial."""
    for name in ("rows", "episodes"):
        listed = said.get(name)
        if isinstance(listed, list):
            for item in listed:
                if isinstance(item, Mapping) and isinstance(item.get("trial"), int):
                    yield item
