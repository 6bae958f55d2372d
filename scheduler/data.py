"""The archived data a controller learns from: pinned at submit time, mounted at run time.

``lab.toml``'s ``[data]`` (``scheduler.controller.DataSpec``) names trials by id and/or
a query (task, kind, outcome, user, limit). When the trial is **submitted** (or run by
``labd run``) it is resolved against an archive to a fixed list of records, each
pinned with its blob digest and its data digest (``repository.trial.PinnedRecord``).
That list is kept with the trial and written into its manifest, so a rerun learns from
exactly the same bytes, whatever was filed since.

Only public, finished trials with a readable record are taken; a query takes the newest
first, up to its ``limit``. Resolution refuses (``InvalidData``, a 422 at the API) a
query that matches nothing, one that matches more than the lab's cap (``DataPolicy``)
without a limit that keeps under it, an id that does not exist, is not public or has no
record, and data larger than the lab's size limit.

When the trial **runs**, ``materialize`` fetches each record from the archive's blob
store (checked against its blob digest as it is read), recomputes its data digest
(``TrialHost.data_digest``) and refuses a record that no longer matches
(``DataUnavailable``: the trial is an error, nothing is mounted). The folder, made once
per data set and cached, is mounted read-only in the sandbox at ``LAB_DATA_DIR``:

    data.json                     the pinned records: trial, kind, task, seed, outcome,
                                  data digest, blob digest, size, and the file's path
    records/trial-<id>.mcap       each record as archived (MCAP, ROS 2 profile)
    lerobot/<task>/...            one LeRobot v3.0 dataset per task, one episode per
                                  record (``TrialHost.dataset``; docs/tasks.md, exports)
    lerobot/<task>/arrays.npz     the same frames as NumPy arrays, for a controller that
                                  has only NumPy

The layout is documented for controllers in docs/trials.md.
"""

from __future__ import annotations

import hashlib
import json
import logging
import shutil
import uuid
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

from repository.blobs import BlobStore
from repository.errors import ArchiveError, RecordNotFound
from repository.index import Filters, Index
from repository.trial import PinnedRecord, Status, Trial
from repository.units import GiB, MiB
from scheduler.client import ApiClient, refusal
from scheduler.controller import DataQuery, DataSpec
from scheduler.errors import DataUnavailable, InvalidData, QueueError
from scheduler.host import TrialHost

log = logging.getLogger("scheduler.data")
LAYOUT = "labd.data/1"  # the folder's layout; part of the cache key
INDEX = "data.json"


@dataclass(frozen=True)
class DataPolicy:
    """How much archived data one trial may pin (the operator's choice)."""

    max_trials: int = 200
    max_bytes: int = 2 * GiB


class Blobs(Protocol):
    """Where a pinned record's bytes come from: the blob store, or a lab's HTTP API."""

    def copy_to(self, digest: str, dest: str | Path) -> Path:
        """The blob ``digest`` into ``dest``, checked against its digest."""
        ...


class Archive(Blobs, Protocol):
    """Where ``[data]`` is resolved: a lab's index and blob store, or its HTTP API."""

    def trial(self, trial_id: int) -> Trial:
        """The trial's record (``RecordNotFound``)."""
        ...

    def find(self, filters: Filters, limit: int) -> list[Trial]:
        """Up to ``limit`` trials matching ``filters``, newest first."""
        ...


class LocalArchive:
    """An archive on this machine: the index and the blob store of a lab's data folder."""

    def __init__(self, index: Index, store: BlobStore) -> None:
        self.index = index
        self.store = store

    def trial(self, trial_id: int) -> Trial:
        return self.index.readable(trial_id)

    def find(self, filters: Filters, limit: int) -> list[Trial]:
        return self.index.find(filters, limit=limit).items

    def copy_to(self, digest: str, dest: str | Path) -> Path:
        return self.store.copy_to(digest, dest)


class RemoteArchive:
    """A lab's archive through its public HTTP API (``labd run --server``): trials are
    read from ``/api/trials``, records downloaded from ``/api/trials/{id}/data.mcap`` and
    checked against their digest."""

    def __init__(self, client: ApiClient) -> None:
        self.client = client
        self.blobs: dict[str, int] = {}  # a record's blob digest -> its trial

    def trial(self, trial_id: int) -> Trial:
        response = self.client.http.get(f"/api/trials/{trial_id}")
        if response.status_code == 404:
            raise RecordNotFound("trial", str(trial_id))
        if response.status_code >= 400:
            raise refusal(response)
        found: dict[str, Any] = response.json()
        mcap = found.get("mcap") or {}
        found.update(mcap=mcap.get("digest"), mcap_size=mcap.get("size"))
        for name in ("worker", "stdout", "stderr"):
            found.setdefault(name, None)
        trial = Trial.model_validate(found)
        if trial.mcap:
            self.blobs[trial.mcap] = trial.id
        return trial

    def find(self, filters: Filters, limit: int) -> list[Trial]:
        params: dict[str, str | int] = {"limit": min(500, max(limit * 2, 50))}
        if filters.task is not None:
            params["task"] = filters.task
        if filters.submitter is not None:
            params["user"] = filters.submitter
        for name in ("kind", "outcome", "status"):
            value = getattr(filters, name)
            if value is not None:
                params[name] = value.value
        listed = self.client.request("GET", "/api/trials", params=params).json()["trials"]
        found: list[Trial] = []
        for row in listed:
            if row["public"] and row.get("mcap") and len(found) < limit:
                found.append(self.trial(int(row["id"])))
        return found

    def copy_to(self, digest: str, dest: str | Path) -> Path:
        dest = Path(dest)
        trial = self.blobs.get(digest)
        if trial is None:
            raise ArchiveError(f"no trial of this archive has the record {digest}")
        dest.parent.mkdir(parents=True, exist_ok=True)
        self.client.download(f"/api/trials/{trial}/data.mcap", dest, digest=digest)
        return dest


def resolve(
    spec: DataSpec, archive: Archive, policy: DataPolicy | None = None
) -> list[PinnedRecord]:
    """``[data]`` as a fixed list of records, by trial id (``InvalidData``)."""
    policy = policy or DataPolicy()
    if len(spec.trials) > policy.max_trials:  # refused before looking any of them up
        raise InvalidData(
            f"it names {len(spec.trials)} trials, more than this lab's limit of {policy.max_trials}"
        )
    chosen: dict[int, PinnedRecord] = {}
    for trial_id in spec.trials:
        try:
            trial = archive.trial(trial_id)
        except RecordNotFound:
            raise InvalidData(f"trial {trial_id} does not exist in this archive") from None
        problem = _unusable(trial)
        if problem:
            raise InvalidData(f"trial {trial_id} {problem}")
        chosen[trial_id] = pin(trial)
    if spec.query is not None:
        for trial in _query(spec.query, archive, policy):
            chosen.setdefault(trial.id, pin(trial))
    if len(chosen) > policy.max_trials:
        raise InvalidData(
            f"it pins {len(chosen)} trials, more than this lab's limit of {policy.max_trials}"
        )
    size = sum(p.size for p in chosen.values())
    if size > policy.max_bytes:
        raise InvalidData(
            f"its {len(chosen)} records hold {size / MiB:.1f} MiB, more than this lab's limit"
            f" of {policy.max_bytes / MiB:.1f} MiB: pin fewer (a smaller limit)"
        )
    return [chosen[i] for i in sorted(chosen)]


def _query(query: DataQuery, archive: Archive, policy: DataPolicy) -> list[Trial]:
    if query.limit is not None and query.limit > policy.max_trials:
        raise InvalidData(
            f"query.limit is {query.limit}, more than this lab's limit of {policy.max_trials}"
            " trials"
        )
    filters = Filters(
        task=query.task,
        kind=query.kind,
        outcome=query.outcome,
        submitter=query.user,
        status=Status.FINISHED,
        public=True,
        has_record=True,
    )
    wanted = query.limit if query.limit is not None else policy.max_trials
    found = archive.find(filters, wanted + 1)
    described = _describe(query)
    if not found:
        raise InvalidData(
            f"the query ({described}) matches no public, finished trial with a record"
        )
    if query.limit is None and len(found) > policy.max_trials:
        raise InvalidData(
            f"the query ({described}) matches more than {policy.max_trials} trials, this"
            " lab's limit: give it a limit (the newest are taken)"
        )
    return found[:wanted]


def _describe(query: DataQuery) -> str:
    fields = [
        f"{name} = {str(value)!r}"
        for name, value in vars(query).items()
        if value is not None and name != "limit"
    ]
    return ", ".join(fields) or "any trial"


def _unusable(trial: Trial) -> str | None:
    """Why a trial's record cannot be learnt from, or None."""
    if not trial.public:
        return "is not public: only public records may be pinned, so anyone can rerun"
    if trial.status is not Status.FINISHED:
        return f"has not finished (it is {trial.status.value})"
    if not trial.mcap or not trial.data_digest or not trial.digest_topics:
        return "has no record to learn from (it ended before recording)"
    return None


def pin(trial: Trial) -> PinnedRecord:
    """The pinned form of a trial whose record is usable."""
    assert trial.mcap and trial.data_digest and trial.digest_topics is not None
    return PinnedRecord(
        trial=trial.id,
        kind=trial.kind,
        task=trial.task,
        seed=trial.seed,
        outcome=trial.outcome,
        data_digest=trial.data_digest,
        digest_topics=list(trial.digest_topics),
        mcap=trial.mcap,
        size=trial.mcap_size or 0,
    )


def data_key(records: Sequence[PinnedRecord]) -> str:
    """The name of a data set's folder in the cache: its records and the folder layout."""
    entries = [r.manifest_entry() for r in records]
    text = json.dumps({"layout": LAYOUT, "records": entries}, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:32]


def materialize(
    records: Sequence[PinnedRecord], archive: Blobs, host: TrialHost, cache: Path
) -> Path:
    """The folder of ``records`` for ``LAB_DATA_DIR``, made (checked) or found in ``cache``.

    ``DataUnavailable`` if a record is gone, damaged, or no longer has its pinned data
    digest: then no folder is left behind.
    """
    folder = cache / "data" / data_key(records)
    if (folder / INDEX).is_file():
        return folder
    partial = folder.with_name(f".{folder.name}.{uuid.uuid4().hex}.partial")
    partial.mkdir(parents=True)
    try:
        files: list[tuple[PinnedRecord, Path]] = []
        for record in records:
            path = partial / "records" / f"trial-{record.trial}.mcap"
            try:
                archive.copy_to(record.mcap, path)
            except (ArchiveError, QueueError, OSError) as err:
                raise DataUnavailable(record.trial, f"could not be read: {err}") from None
            found = host.data_digest(path, record.digest_topics)
            if found != record.data_digest:
                raise DataUnavailable(
                    record.trial,
                    f"no longer has the data digest it was pinned with ({found[:12]}..., not"
                    f" {record.data_digest[:12]}...): it was changed since; it is not mounted",
                )
            files.append((record, path))
        host.dataset(files, partial / "lerobot")
        index = [
            {
                **record.model_dump(mode="json"),
                "path": f"records/trial-{record.trial}.mcap",
            }
            for record in records
        ]
        (partial / INDEX).write_text(json.dumps(index, indent=2) + "\n")
        _read_only(partial)
        if folder.exists():  # another worker made it meanwhile
            shutil.rmtree(partial, ignore_errors=True)
        else:
            partial.rename(folder)
    except BaseException:
        shutil.rmtree(partial, ignore_errors=True)
        raise
    log.info("data set %s: %d records", folder.name, len(records))
    return folder


def _read_only(folder: Path) -> None:
    """Files 0444 and folders 0555: readable by the sandbox's user, written by no one."""
    for path in sorted(folder.rglob("*"), reverse=True):
        path.chmod(0o555 if path.is_dir() else 0o444)
    folder.chmod(0o555)
