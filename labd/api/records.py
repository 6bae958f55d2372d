"""What the API makes from records: exports for learning, kept as derived artifacts.

    GET /api/trials/{id}/export/{format}            one trial's export (its file, or a zip)
    GET /api/trials/{id}/export/{format}/signature  the lab's signature of that export
    GET /api/exports/{format}?trials=..&task=..     many trials as one dataset (a zip), one
                                                    episode per trial: ids and/or a query

The formats are those of ``repository.formats`` (``parquet``: one Parquet file, a row
per control tick; ``lerobot``: a LeRobot v3.0 dataset, as a zip of its folder); what a
route says of a format (its media type, its file names) is what the format declares.

An export of one trial is made the first time it is asked for, from the record checked
against its digest, and kept in the blob store beside the record
(``repository.index.Derived``): it never changes the record or its digests, and later
requests are served from the store. An export of many trials (its trials chosen as
lab.toml's ``[data]`` chooses them, ``scheduler.data``, under the same limits) is kept
on disk under the trials' ids and data digests (``labd.api.builds``), and served from
there while the same trials are asked for. Each export is built once however many ask
at once, and one at a time: anyone may ask, and a build takes seconds of CPU.

Each export carries the record's signature in its provenance, and is signed itself: the
lab signs the digests of its files (``repository.signing``), kept in the export as
``labd-signature.json`` (in the LeRobot zip; served beside the Parquet file), so that
``labd verify DIR`` tells whether any file of it was changed.
"""

from __future__ import annotations

import hashlib
import json
import shutil
import tempfile
from pathlib import Path
from typing import Annotated, Any

from anyio import to_thread
from fastapi import APIRouter, Depends, Query
from fastapi.responses import FileResponse, StreamingResponse
from pydantic import AfterValidator, BaseModel, Field, WithJsonSchema
from pydantic_core import PydanticCustomError

from labd import __version__
from labd.api.builds import Builds
from labd.api.common import Lab, blob_response
from labd.api.errors import ApiError, responses
from labd.api.models import Id
from labd.api.state import App
from labd.exports import export_records
from labd.videos import ASK_WAIT, VideoUnavailable
from repository.digests import readable_json
from repository.export import ExportFormat
from repository.formats import FORMATS
from repository.index import Derived
from repository.signing import EXPORT, file_digests
from repository.trial import MAX_ID, Kind, Outcome, Trial
from repository.well_known import (
    EXPORT_SIGNATURE,
    RECORD_FILE,
    REPLAY,
)
from scheduler.controller import DataQuery, DataSpec
from scheduler.data import LocalArchive, resolve

router = APIRouter(tags=["data"])


async def _builds(app: App) -> Builds:
    """The app's export builds (``labd.api.state``)."""
    return app.builds


Building = Annotated[Builds, Depends(_builds)]


def _known(name: str) -> str:
    if name not in FORMATS:
        *first, last = (repr(n) for n in FORMATS)
        expected = f"{', '.join(first)} or {last}" if first else last
        raise PydanticCustomError(
            "literal_error", "Input should be {expected}", {"expected": expected}
        )
    return name


# A format's name in a path: one of the formats, an enum in the OpenAPI document.
FormatName = Annotated[
    str, AfterValidator(_known), WithJsonSchema({"type": "string", "enum": list(FORMATS)})
]


async def _format(fmt: FormatName) -> ExportFormat:
    return FORMATS[fmt]


Format = Annotated[ExportFormat, Depends(_format)]


def provenance(trial: Trial, url: str) -> dict[str, Any]:
    """What an export says of where it came from: the trial, its code, its digests."""
    return {
        "trial": trial.id,
        "url": url,
        "repository": trial.repository,
        "commit": trial.commit,
        "task": trial.task,
        "kind": trial.kind.value,
        "seed": trial.seed,
        "outcome": trial.outcome.value if trial.outcome else None,
        "manifest_digest": trial.manifest_digest,
        "data_digest": trial.data_digest,
        "manifest": trial.manifest,
        "signature": trial.signature,
    }


@router.get(
    "/api/trials/{trial_id}/export/{fmt}",
    response_class=StreamingResponse,
    responses={
        200: {
            "content": {f.media_type: {} for f in FORMATS.values()},
            "description": "the export: " + "; or ".join(f.doc for f in FORMATS.values()),
        },
        **responses(403, 404, 422, 500, 503),
    },
)
async def export_record(
    trial_id: Id, fmt: Format, service: Lab, builds: Building
) -> StreamingResponse:
    """The trial's observation-action pairs in the format: Parquet, or a LeRobot dataset
    (zip)."""
    item = await _artifact(service, builds, trial_id, fmt)
    filename = fmt.filename(trial_id)
    return await to_thread.run_sync(blob_response, service, item.digest, item.media_type, filename)


@router.get(
    "/api/trials/{trial_id}/export/{fmt}/signature", responses=responses(403, 404, 422, 500, 503)
)
async def export_signature(
    trial_id: Id, fmt: Format, service: Lab, builds: Building
) -> dict[str, Any]:
    """The lab's signature of the export: the digests of its files, signed."""
    await _artifact(service, builds, trial_id, fmt)

    def read() -> dict[str, Any]:
        signed = service.index.derived(trial_id)[fmt.artifact + ".sig"]
        data: dict[str, Any] = json.loads(service.store.read_bytes(signed.digest))
        return data

    return await to_thread.run_sync(read)


async def _artifact(service: Lab, builds: Builds, trial_id: int, fmt: ExportFormat) -> Derived:
    """The trial's export, built the first time it is asked for (once, however many ask)."""
    made = await to_thread.run_sync(_made, service, trial_id, fmt)
    if made is not None:
        return made

    def build() -> Derived:  # unless the build before this one's turn made it
        return _made(service, trial_id, fmt) or _make(
            service, service.index.readable(trial_id), fmt
        )

    return await builds.once(f"trial-{trial_id}-{fmt.name}", build)


def _made(service: Lab, trial_id: int, fmt: ExportFormat) -> Derived | None:
    """The trial's export as kept beside its record, or None if not made yet."""
    trial = service.index.readable(trial_id)
    if not trial.mcap:
        raise ApiError(404, f"trial {trial_id} has no record to export")
    made = service.index.derived(trial_id)
    name = fmt.artifact
    if name in made and name + ".sig" in made:
        return made[name]
    return None


def _make(service: Lab, trial: Trial, fmt: ExportFormat) -> Derived:
    assert trial.mcap is not None
    with tempfile.TemporaryDirectory(prefix="labd-export-") as folder:
        work = Path(folder)
        mcap = work / RECORD_FILE
        service.store.copy_to(trial.mcap, mcap)  # checked against its digest
        out = work / "export"
        export_records([(mcap, provenance(trial, f"/api/trials/{trial.id}"))], out, fmt)
        sig_bytes = _sign(service, out, fmt, [trial])
        if fmt.served is not None:
            artifact = out / fmt.served
        else:
            artifact = Path(shutil.make_archive(str(work / fmt.name), "zip", out))
        digest = service.store.put_file(artifact)
        item = Derived(fmt.artifact, digest, artifact.stat().st_size, fmt.media_type)
        sig_digest = service.store.put_bytes(sig_bytes)
    service.index.put_derived(trial.id, item)
    service.index.put_derived(
        trial.id, Derived(fmt.artifact + ".sig", sig_digest, len(sig_bytes), "application/json")
    )
    return item


def _sign(service: Lab, out: Path, fmt: ExportFormat, trials: list[Trial]) -> bytes:
    """Sign the export in ``out`` (the digests of its files); its signature, also written
    into the folder as ``labd-signature.json``."""
    statement: dict[str, Any] = {"schema": EXPORT, "format": fmt.name, "files": file_digests(out)}
    if len(trials) == 1:
        statement.update(trial=trials[0].id, data_digest=trials[0].data_digest)
    else:
        statement["trials"] = [{"trial": t.id, "data_digest": t.data_digest} for t in trials]
    signed = service.keyring.sign(statement)
    sig_bytes = readable_json(signed.to_json())
    (out / EXPORT_SIGNATURE).write_bytes(sig_bytes)
    return sig_bytes


@router.get(
    "/api/exports/{fmt}",
    response_class=FileResponse,
    responses={
        200: {
            "content": {"application/zip": {}},
            "description": "a zip of the export's folder: one episode per trial, signed",
        },
        **responses(404, 422, 500, 503),
    },
)
async def export_many(
    fmt: Format,
    service: Lab,
    builds: Building,
    *,
    trials: list[Id] = Query(default=[], description="trial ids"),  # noqa: B008
    task: str | None = None,
    kind: Kind | None = None,
    outcome: Outcome | None = None,
    user: str | None = None,
    limit: int | None = Query(default=None, ge=1, le=MAX_ID),
) -> FileResponse:
    """Many trials as one dataset: ids and/or a query (as lab.toml's ``[data]``), newest
    first up to ``limit``, one episode per trial, with each one's provenance. Made once
    for the same trials (as their ids and data digests say) and kept."""
    query = None
    if any(v is not None for v in (task, kind, outcome, user, limit)):
        query = DataQuery(
            task=task,
            kind=kind,
            outcome=outcome,
            user=user,
            limit=limit,
        )
    if not trials and query is None:
        raise ApiError(422, "name trials (trials=12&trials=15) and/or a query (task=..., ...)")
    spec = DataSpec(tuple(trials), query)

    def choose() -> list[Trial]:
        archive = LocalArchive(service.index, service.store)
        pinned = resolve(spec, archive, service.config.data_policy)
        return [service.index.trial(p.trial) for p in pinned]

    chosen = await to_thread.run_sync(choose)
    key = _many_key(service, fmt, chosen)
    path = await to_thread.run_sync(builds.kept, key)
    if path is None:

        def build() -> Path:  # unless the build before this one's turn made it
            return builds.kept(key) or _make_many(service, builds, key, fmt, chosen)

        path = await builds.once(key, build)
    return FileResponse(
        path, media_type="application/zip", filename=f"export-{len(chosen)}-trials-{fmt.name}.zip"
    )


def _many_key(service: Lab, fmt: ExportFormat, chosen: list[Trial]) -> str:
    """What names an export of many trials: its format, its trials and their data, the
    key that signs it and the lab's version (a newer lab may export differently)."""
    named = {
        "format": fmt.name,
        "trials": [[t.id, t.data_digest] for t in chosen],
        "key": service.keyring.current,
        "labd": __version__,
    }
    return hashlib.sha256(json.dumps(named, sort_keys=True).encode()).hexdigest()[:32]


def _make_many(
    service: Lab, builds: Builds, key: str, fmt: ExportFormat, chosen: list[Trial]
) -> Path:
    folder = builds.scratch()
    try:
        archive = LocalArchive(service.index, service.store)
        records = []
        for trial in chosen:
            assert trial.mcap is not None
            mcap = archive.copy_to(trial.mcap, folder / "records" / f"trial-{trial.id}.mcap")
            records.append((mcap, provenance(trial, f"/api/trials/{trial.id}")))
        out = folder / "export"
        export_records(records, out, fmt)
        _sign(service, out, fmt, chosen)
        made = shutil.make_archive(str(folder / f"export-{fmt.name}"), "zip", out)
        return builds.keep(key, Path(made))
    finally:
        shutil.rmtree(folder, ignore_errors=True)


class ReplayVerdict(BaseModel):
    """What replaying the trial's record gave, in the worker, after it was filed."""

    verified: bool
    ticks: int
    compared: int = Field(description="messages compared with the record")
    divergence: dict[str, Any] | None = Field(description="tick, topic, what differed")
    said: str = Field(description="the verdict in words")
    video: dict[str, Any] | None = Field(description="camera, frames, fps of the video")
    node: str | None = Field(
        default=None,
        description="where it was replayed: the cluster's node (ray:ID) for a trial a node"
        " of the lab's Ray cluster ran (null: in the lab, or by the worker that ran it)",
    )


@router.get("/api/trials/{trial_id}/replay", responses=responses(403, 404, 500))
def replay_verdict(trial_id: Id, service: Lab) -> ReplayVerdict:
    """The verdict of replaying the trial's record from its actions (made when filed)."""
    service.index.readable(trial_id)
    item = service.index.derived(trial_id).get(REPLAY)
    if item is None:
        raise ApiError(404, f"trial {trial_id} has not been replayed")
    return ReplayVerdict.model_validate_json(service.store.read_bytes(item.digest))


@router.get(
    "/api/trials/{trial_id}/video",
    response_class=StreamingResponse,
    responses={
        200: {"content": {"video/mp4": {}}, "description": "H.264 MP4"},
        **responses(403, 404, 500, 503),
    },
)
async def video(trial_id: Id, service: Lab) -> StreamingResponse:
    """The task's first camera through the whole trial, rendered by replaying its record:
    the first time it is asked for (which may take a while: 503 with ``Retry-After``
    after two minutes, while the rendering goes on), or earlier, in the background."""
    trial = await to_thread.run_sync(service.index.readable, trial_id)
    if not trial.mcap:
        raise ApiError(404, f"trial {trial_id} has no record, so no video")
    try:
        item = await service.videos.ask(trial_id, ASK_WAIT)
    except VideoUnavailable as err:
        raise ApiError(404, str(err)) from None
    except TimeoutError:
        raise ApiError(
            503,
            f"trial {trial_id}'s video is being rendered; ask again in a moment",
            headers={"Retry-After": "10"},
        ) from None
    return await to_thread.run_sync(blob_response, service, item.digest, "video/mp4", None)
