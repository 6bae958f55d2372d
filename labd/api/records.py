"""What the API makes from a record: exports for learning, kept as derived artifacts.

    GET /api/trials/{id}/export/parquet        one Parquet file of observation-action pairs
    GET /api/trials/{id}/export/lerobot        a LeRobot v3.0 dataset, as a zip of its folder

An export is made the first time it is asked for, from the record checked against its
digest, and kept in the blob store beside the record (``repository.index.Derived``): it
never changes the record or its digests, and later requests are served from the store.
"""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path
from typing import Any, Literal

from fastapi import APIRouter
from fastapi.responses import StreamingResponse

from labd.api.common import Lab, blob_response
from labd.api.errors import ApiError, responses
from labd.sim import registry
from repository.export import export
from repository.index import Derived
from repository.trial import Trial

router = APIRouter(tags=["data"])
Format = Literal["parquet", "lerobot"]
ARTIFACT: dict[str, tuple[str, str]] = {  # format -> (derived name, media type)
    "parquet": ("export.parquet", "application/vnd.apache.parquet"),
    "lerobot": ("export-lerobot.zip", "application/zip"),
}


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
    trial = service.index.trial(trial_id)
    if not trial.mcap:
        raise ApiError(404, f"trial {trial_id} has no record to export")
    name, media = ARTIFACT[fmt]
    item = service.index.derived(trial_id).get(name)
    if item is None:
        item = _make(service, trial, fmt)
    filename = f"trial-{trial_id}.parquet" if fmt == "parquet" else f"trial-{trial_id}-lerobot.zip"
    return blob_response(service, item.digest, media, filename)


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
        if fmt == "parquet":
            artifact = out / "data.parquet"
        else:
            artifact = Path(shutil.make_archive(str(work / "lerobot"), "zip", out))
        digest = service.store.put_file(artifact)
        item = Derived(name, digest, artifact.stat().st_size, media)
    service.index.put_derived(trial.id, item)
    return item
