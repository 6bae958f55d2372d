"""The one check of a worker's filing, before the lab files and signs it.

A worker (inside ``labd serve``, or ``labd worker`` on another machine with a worker's
token) runs a trial it claimed and files what came out (``repository.trial.Filing``):
the record it uploaded (a blob, named by its sha256) and what it says the record holds.
The lab signs what it files, so it files only what it read in the record itself
(``FilingCheck``, which ``Queue.finish`` calls before it stores anything):

- the record's manifest is the trial's own: the repository, commit, task (at the version
  this lab runs), parameters (the task's full values), seed and pinned data the lab
  gave with the claim; the filing's manifest is the record's, and its manifest digest
  is that manifest's;
- its digest topics are the task's, and its data digest is the record's, recomputed;
- its status, outcome, reason and metrics are what the record's ``outcome.json`` says,
  and its logs are the record's attachments, byte for byte;
- its size is the blob's;
- a rerun's verdict (``reproduced``) is whether that data digest is the original's;
- a filing without a record is an error or a cancellation that claims no data digest
  and no metrics: there would be nothing to check them against (its logs, which no
  signature names, are kept: they say why it broke).

Anything else is a ``FilingRefused`` naming every difference (the API answers 422 with
it), and nothing is filed or signed. The lab's signature then vouches that the record is
the trial's own and internally consistent: its bytes, its manifest, its data digest, its
outcome and metrics are those the lab signed. It does not vouch that the physics ran as
recorded: the replay verdict does (``GET /api/trials/{id}/replay``: the task rebuilt and
fed the recorded commands). Nor that the worker ran the trial rather than filing the
record of a trial with the same manifest: a rerun's record is, byte for byte, the record
of the trial it reruns.
"""

from __future__ import annotations

import tempfile
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

from repository.digests import canonical_json, manifest_digest
from repository.errors import ManifestError
from repository.manifest import Manifest
from repository.trial import Filing, Kind, Outcome, Status, Trial, Value
from repository.well_known import LOGS, RECORD_FILE, side_logs
from scheduler.errors import FilingRefused, TrialError
from scheduler.host import RecordFacts, TrialHost


class Store(Protocol):
    """Where filed records are: the lab's blob store."""

    def copy_to(self, digest: str, dest: str | Path) -> Path: ...
    def size(self, digest: str) -> int: ...


@dataclass(frozen=True)
class Expected:
    """What this lab expects of a trial's record, from the task and the claim."""

    values: Mapping[str, Value]  # the task's full parameter values
    version: str  # the task's version here
    digest_topics: list[str]  # sorted
    sides: tuple[str, ...] = ()  # a task teams play: its sides, home first

    def logs(self, trial: Trial) -> dict[str, str]:
        """The attachments a trial's ``stdout`` and ``stderr`` are (a leg's: home's)."""
        return side_logs(self.sides[0]) if trial.kind is Kind.MATCH and self.sides else LOGS


@dataclass(frozen=True)
class Claims:
    """What a filing, or a signed statement, says a record holds (None: says nothing)."""

    manifest_digest: str | None
    data_digest: str | None
    status: str | None = None
    outcome: str | None = None
    reason: str | None = None
    metrics: Mapping[str, Any] | None = None


def record_differences(claims: Claims, facts: RecordFacts) -> list[str]:
    """Where ``claims`` say other than the record: each difference in words, with the
    name of the field that says it (a filing's and a statement's share names)."""
    problems = []
    if facts.manifest is None:
        problems.append("manifest_digest: the record holds no manifest")
    elif (digest := manifest_digest(facts.manifest)) != claims.manifest_digest:
        problems.append(
            f"manifest_digest: the record's manifest has digest {digest},"
            f" not {claims.manifest_digest}"
        )
    if facts.data_digest != claims.data_digest:
        problems.append(
            f"data_digest: the record's data digest is {facts.data_digest},"
            f" not {claims.data_digest}"
        )
    said = facts.outcome
    if said is None or "outcome" not in said:
        if claims.status is not None:  # a trial's record says how it ended
            problems.append("outcome: the record holds no outcome.json saying how it ended")
        return problems
    for name in ("status", "outcome", "reason"):
        claimed = getattr(claims, name)
        if claimed is not None and said.get(name) != claimed:
            problems.append(f"{name}: the record says {said.get(name)!r}, not {claimed!r}")
    recorded = said.get("metrics") or {}
    if claims.metrics is not None and not _same(recorded, claims.metrics):
        changed = sorted(
            key
            for key in set(recorded) | set(claims.metrics)
            if not _same(recorded.get(key), claims.metrics.get(key))
        )
        problems.append(f"metrics: the record's differ in {', '.join(changed)}")
    return problems


def manifest_problems(held: Mapping[str, Any], trial: Trial, expected: Expected) -> list[str]:
    """Where the manifest ``held`` (as a filing or a record holds it) is not the trial's
    own, in words."""
    try:
        manifest = Manifest.from_json(held)
    except ManifestError as err:
        return [f"manifest: it is not one the lab writes ({err})"]
    pinned = [p.manifest_entry() for p in trial.data] if trial.data else None
    code: dict[str, tuple[Any, Any]] = {
        "repository": (manifest.repository, trial.repository),
        "commit": (manifest.commit, trial.commit),
    }
    if trial.kind is Kind.MATCH or manifest.kind is Kind.MATCH:
        code = _teams(manifest, trial, expected.sides)
    pairs = {
        **code,
        "task": (manifest.task.name, trial.task),
        "task version": (manifest.task.version, expected.version),
        "parameters": (dict(manifest.parameters), dict(expected.values)),
        "seed": (manifest.seed, trial.seed),
        "data": ([p.to_json() for p in manifest.data] or None, pinned),
    }
    return [
        f"manifest: its {name} is {canonical_json(got)},"
        f" trial {trial.id}'s is {canonical_json(want)}"
        for name, (got, want) in pairs.items()
        if not _same(got, want)
    ]


def _teams(manifest: Manifest, trial: Trial, sides: tuple[str, ...]) -> dict[str, tuple[Any, Any]]:
    """A leg's teams as its manifest names them, and as its trial does: its own code at
    home (the first side), its ``away_*`` team at the second."""
    teams = manifest.teams
    home, away = (teams.get(side) for side in (*sides, "", "")[:2])
    return {
        "kind": (manifest.kind.value, trial.kind.value),
        "sides": (sorted(teams), sorted(sides)),
        "repository": (home.code.repository if home else None, trial.repository),
        "commit": (home.code.commit if home else None, trial.commit),
        "away repository": (away.code.repository if away else None, trial.away_repository),
        "away commit": (away.code.commit if away else None, trial.away_commit),
    }


def _same(a: Any, b: Any) -> bool:
    """Values compared as their canonical JSON, so NaN equals NaN and key order is moot."""
    return canonical_json(a) == canonical_json(b)


def filing_problems(
    trial: Trial,
    filing: Filing,
    record: RecordFacts | None,
    *,
    expected: Expected,
    size: int | None = None,
    original: Trial | None = None,
) -> list[str]:
    """Every way ``filing`` says other than ``record`` (the file its ``mcap`` names, read
    by the lab; None without one) and the trial; empty when the lab may sign it."""
    problems = []
    if filing.manifest is not None:
        problems += manifest_problems(filing.manifest, trial, expected)
        if filing.manifest_digest not in (None, manifest_digest(filing.manifest)):
            problems.append("manifest_digest: it is not the digest of the filing's manifest")
    if record is None:
        if filing.status is Status.FINISHED and filing.outcome is not Outcome.ERROR:
            problems.append(
                f"outcome: a filing without a record (mcap) is an error or a cancellation;"
                f" there is no record to bear out {filing.outcome}"
            )
        for name in ("data_digest", "metrics"):
            if getattr(filing, name) is not None:
                problems.append(f"{name}: a filing without a record (mcap) claims none")
        if filing.reproduced:
            problems.append("reproduced: a rerun without a record reproduced nothing")
        return problems
    if size is not None and filing.mcap_size != size:
        problems.append(f"mcap_size: the record is {size:,} bytes, not {filing.mcap_size!r}")
    if record.manifest is not None:
        problems += [
            p for p in manifest_problems(record.manifest, trial, expected) if p not in problems
        ]
        if filing.manifest is not None and not _same(filing.manifest, record.manifest):
            problems.append("manifest: the filing's is not the one the record holds")
    if sorted(filing.digest_topics or []) != expected.digest_topics:
        problems.append(
            f"digest_topics: the task's are {', '.join(expected.digest_topics)};"
            f" the filing names {', '.join(sorted(filing.digest_topics or [])) or 'none'}"
        )
    claims = Claims(
        filing.manifest_digest,
        filing.data_digest,
        filing.status.value,
        filing.outcome.value if filing.outcome else None,
        filing.reason,
        filing.metrics or {},
    )
    problems += record_differences(claims, record)
    for stream, name in expected.logs(trial).items():
        claimed = getattr(filing, stream)
        if claimed is not None and record.attachments.get(name) != claimed:
            problems.append(f"{stream}: the record's {name} is not the blob {claimed}")
    problems += _verdict(trial, filing, record, original)
    return problems


def _verdict(
    trial: Trial, filing: Filing, record: RecordFacts, original: Trial | None
) -> list[str]:
    """A rerun reproduced exactly when its data digest is the original's."""
    if trial.rerun_of is None:
        if filing.reproduced is not None:
            return [f"reproduced: trial {trial.id} reruns no trial"]
        return []
    if original is None or not original.data_digest:
        return ["reproduced: the original has no record to reproduce"] if filing.reproduced else []
    same = record.data_digest == original.data_digest
    if bool(filing.reproduced) != same:
        return [
            f"reproduced: the record's data digest {'is' if same else 'is not'} trial"
            f" {original.id}'s, so it is {same}"
        ]
    return []


class FilingCheck:
    """Reads the record a filing names from ``store`` (through ``host``) and refuses the
    filing (``FilingRefused``) where it says otherwise (``filing_problems``)."""

    def __init__(self, store: Store, host: TrialHost) -> None:
        self.store = store
        self.host = host

    def expected(self, trial: Trial) -> Expected:
        return Expected(
            values=self.host.check(trial.task, trial.params),
            version=self.host.task_version(trial.task),
            digest_topics=sorted(self.host.digest_topics(trial.task)),
            sides=tuple(self.host.sides(trial.task)),
        )

    def __call__(self, trial: Trial, filing: Filing, original: Trial | None) -> None:
        """Refuse ``filing`` of ``trial`` unless its record bears it out."""
        expected = self.expected(trial)
        record, size = None, None
        if filing.mcap is not None:
            with tempfile.TemporaryDirectory(prefix="labd-filing-") as folder:
                path = self.store.copy_to(filing.mcap, Path(folder) / RECORD_FILE)
                size = path.stat().st_size
                try:
                    record = self.host.read_record(path, expected.digest_topics)
                except TrialError as err:
                    raise FilingRefused(trial.id, [f"mcap: {err}"]) from None
        problems = filing_problems(
            trial, filing, record, expected=expected, size=size, original=original
        )
        if problems:
            raise FilingRefused(trial.id, problems)
