"""What the API makes from a record: exports for learning, kept as derived artifacts.

    GET /api/trials/{id}/export/parquet             one Parquet file of observation-action pairs
    GET /api/trials/{id}/export/lerobot             a LeRobot v3.0 dataset, as a zip of its folder
    GET /api/trials/{id}/export/{format}/signature  the lab's signature of that export

An export is made the first time it is asked for, from the record checked against its
digest, and kept in the blob store beside the record (``repository.index.Derived``): it
never changes the record or its digests, and later requests are served from the store.

Each export carries the record's signature in its provenance, and is signed itself: the
lab signs the digests of its files (``repository.signing``), kept in the export as
``labd-signature.json`` (in the LeRobot zip; served beside the Parquet file), so that
``labd verify DIR`` tells whether any file of it was changed.
"""

from __future__ import annotations

import json
import shutil
import tempfile
from pathlib import Path
from typing import Any, Literal

from fastapi import APIRouter
from fastapi.responses import StreamingResponse
from pydantic import BaseModel, Field

from labd.api.common import Lab, blob_response
from labd.api.errors import ApiError, responses
from labd.sim import registry
from repository.export import export
from repository.index import Derived
from repository.signing import EXPORT, file_digests
from repository.trial import Trial
from scheduler.host import REPLAY, VIDEO

router = APIRouter(tags=["data"])
Format = Literal["parquet", "lerobot"]
ARTIFACT: dict[str, tuple[str, str]] = {  # format -> (derived name, media type)
    "parquet": ("export.parquet", "application/vnd.apache.parquet"),
    "lerobot": ("export-lerobot.zip", "application/zip"),
}
SIGNATURE = "labd-signature.json"  # an export's own signature, in its folder


def provenance(trial: Trial, url: str) -> dict[str, Any]:
    """What an export says of where it came from: the trial, its code, its digests."""
    return {
        "trial": trial.id,
        "url": url,
        "repository": trial.repository,
        "commit": trial.commit,
        "task": trial.task,
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
            "content": {"application/vnd.apache.parquet": {}, "application/zip": {}},
            "description": "the export: a Parquet file, or a zip of a LeRobot dataset",
        },
        **responses(404, 422, 500),
    },
)
def export_record(trial_id: int, fmt: Format, service: Lab) -> StreamingResponse:
    """The trial's observation-action pairs as Parquet, or as a LeRobot dataset (zip)."""
    item = _artifact(service, trial_id, fmt)
    filename = f"trial-{trial_id}.parquet" if fmt == "parquet" else f"trial-{trial_id}-lerobot.zip"
    return blob_response(service, item.digest, item.media_type, filename)


@router.get("/api/trials/{trial_id}/export/{fmt}/signature", responses=responses(404, 422, 500))
def export_signature(trial_id: int, fmt: Format, service: Lab) -> dict[str, Any]:
    """The lab's signature of the export: the digests of its files, signed."""
    _artifact(service, trial_id, fmt)
    signed = service.index.derived(trial_id)[ARTIFACT[fmt][0] + ".sig"]
    data: dict[str, Any] = json.loads(service.store.read_bytes(signed.digest))
    return data


def _artifact(service: Lab, trial_id: int, fmt: Format) -> Derived:
    trial = service.index.trial(trial_id)
    if not trial.mcap:
        raise ApiError(404, f"trial {trial_id} has no record to export")
    made = service.index.derived(trial_id)
    name = ARTIFACT[fmt][0]
    if name in made and name + ".sig" in made:
        return made[name]
    return _make(service, trial, fmt)


def _make(service: Lab, trial: Trial, fmt: Format) -> Derived:
    assert trial.mcap is not None
    name, media = ARTIFACT[fmt]
    observations, actions = registry.get(trial.task).topics()
    with tempfile.TemporaryDirectory(prefix="labd-export-") as folder:
        work = Path(folder)
        mcap = work / "trial.mcap"
        service.store.copy_to(trial.mcap, mcap)  # checked against its digest
        out = work / "export"
        export(
            mcap,
            out,
            fmt,
            observations=observations,
            actions=actions,
            provenance=provenance(trial, f"/api/trials/{trial.id}"),
        )
        signed = service.keyring.sign(
            {
                "schema": EXPORT,
                "trial": trial.id,
                "format": fmt,
                "data_digest": trial.data_digest,
                "files": file_digests(out),
            }
        )
        sig_bytes = (json.dumps(signed.to_json(), indent=2, sort_keys=True) + "\n").encode()
        (out / SIGNATURE).write_bytes(sig_bytes)
        if fmt == "parquet":
            artifact = out / "data.parquet"
        else:
            artifact = Path(shutil.make_archive(str(work / "lerobot"), "zip", out))
        digest = service.store.put_file(artifact)
        item = Derived(name, digest, artifact.stat().st_size, media)
        sig_digest = service.store.put_bytes(sig_bytes)
    service.index.put_derived(trial.id, item)
    service.index.put_derived(
        trial.id, Derived(name + ".sig", sig_digest, len(sig_bytes), "application/json")
    )
    return item


class ReplayVerdict(BaseModel):
    """What replaying the trial's record gave, in the worker, after it was filed."""

    verified: bool
    ticks: int
    compared: int = Field(description="messages compared with the record")
    divergence: dict[str, Any] | None = Field(description="tick, topic, what differed")
    said: str = Field(description="the verdict in words")
    video: dict[str, Any] | None = Field(description="camera, frames, fps of the video")


@router.get("/api/trials/{trial_id}/replay", responses=responses(404, 500))
def replay_verdict(trial_id: int, service: Lab) -> ReplayVerdict:
    """The verdict of replaying the trial's record from its actions (made when filed)."""
    service.index.trial(trial_id)
    item = service.index.derived(trial_id).get(REPLAY)
    if item is None:
        raise ApiError(404, f"trial {trial_id} has not been replayed")
    return ReplayVerdict.model_validate_json(service.store.read_bytes(item.digest))


@router.get(
    "/api/trials/{trial_id}/video",
    response_class=StreamingResponse,
    responses={
        200: {"content": {"video/mp4": {}}, "description": "H.264 MP4"},
        **responses(404, 500),
    },
)
def video(trial_id: int, service: Lab) -> StreamingResponse:
    """The task's camera through the whole trial, rendered during its replay."""
    service.index.trial(trial_id)
    item = service.index.derived(trial_id).get(VIDEO)
    if item is None:
        raise ApiError(404, f"trial {trial_id} has no video (it has not been replayed)")
    return blob_response(service, item.digest, "video/mp4", None)
