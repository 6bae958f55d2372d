"""A record's summary for its page: what the trial page draws, without the MCAP.

    GET /api/trials/{id}/summary        plots, camera thumbnails, a map, a 3D scene (JSON)

The worker that filed the trial made the summary (``labd.recorder.summary``) and kept
it beside the record as a derived artifact (``summary.json``, gzip'd JSON); a record
without one (filed before summaries existed, or whose summary failed), or with one of
an older version, gets one made from the record the first time it is asked for. The
stored bytes are sent as they are to a browser that accepts gzip, which they all do.
"""

from __future__ import annotations

import re
import tempfile
import zlib
from pathlib import Path

from fastapi import APIRouter, Request
from fastapi.responses import Response
from pydantic import BaseModel

from labd.api.common import Lab
from labd.api.errors import ApiError, responses
from labd.api.models import Id
from labd.errors import SummaryError
from labd.recorder.summary import VERSION
from repository.index import Derived
from repository.trial import Trial
from repository.well_known import RECORD_FILE, SUMMARY, SUMMARY_MEDIA_TYPE

router = APIRouter(tags=["data"])
SECONDS = 120.0  # to summarize a record on demand
_VERSION = re.compile(rb'^\{"version":(\d+)')


class Plot(BaseModel):
    topic: str
    side: str  # lab (an observation) or client (a command)
    group: str  # the message's field the plot shows ("" for the message itself)
    labels: list[str]
    values: list[list[float | None]]  # one list per label, a value per point


class Camera(BaseModel):
    topic: str
    t: list[float]  # seconds: the time of each frame
    width: int  # of one thumbnail
    height: int
    columns: int  # thumbnails across the sprite, in time order
    source: list[int]  # the camera's width and height
    sprite: str  # a data: URL of one JPEG


class Path_(BaseModel):
    t: list[float]
    x: list[float]
    y: list[float]


class FloorMap(BaseModel):
    frame: str
    walls: list[list[float]]  # x0, y0, x1, y1
    tags: list[list[float]]  # id, x, y, and the normal's x, y
    goal: list[float] | None
    path: Path_


class Episode(BaseModel):
    status: str
    reason: str
    ends: list[list[float | str]]  # [t, status] where an episode ended


class Scene(BaseModel):
    bodies: list[dict[str, object]]  # name, parent, pos, quat (x, y, z, w), joints
    geoms: list[dict[str, object]]  # body, shape, size, pos, quat, rgba, texture, repeat
    textures: list[str]  # PNG data: URLs
    qpos0: list[float]  # the model's joint positions at the first point
    moving: list[int]  # the indices of those that move
    qpos: list[list[float]]  # per point, the moving ones


class UxEvents(BaseModel):
    """A live page's user-experience events (``/ux/events``): counts by kind, and the
    first of them as [t, kind, key, value]."""

    counts: dict[str, int]
    events: list[list[float | str]]


class RecordSummary(BaseModel):
    """A record's summary (``labd.recorder.summary`` describes every field)."""

    version: int
    task: str
    ticks: int
    duration: float
    t: list[float]  # seconds: the time of each point
    tick: list[int]
    plots: list[Plot]
    constant: list[list[str | float]]  # topic, group, label, value: series that never changed
    episode: Episode
    camera: Camera | None
    map: FloorMap | None
    scene: Scene | None
    ux: UxEvents | None = None


@router.get(
    "/api/trials/{trial_id}/summary",
    response_class=Response,
    responses={
        200: {"model": RecordSummary, "description": "the record's summary, for its page"},
        **responses(403, 404, 500),
    },
)
def summary(trial_id: Id, service: Lab, request: Request) -> Response:
    """Plots, camera thumbnails, a map and a 3D scene of the trial's record: what its
    page draws, in a small fraction of the record's size."""
    trial = service.index.readable(trial_id)
    if not trial.mcap:
        raise ApiError(404, f"trial {trial_id} has no record to summarize")
    item = service.index.derived(trial_id).get(SUMMARY)
    blob = service.store.read_bytes(item.digest) if item is not None else None
    if blob is None or _version(blob) != VERSION:
        blob = _make(service, trial)
    headers = {"ETag": f'"{trial_id}-{zlib.crc32(blob):08x}"', "Cache-Control": "no-cache"}
    if "gzip" in request.headers.get("accept-encoding", ""):
        headers["Content-Encoding"] = "gzip"
        headers["Vary"] = "Accept-Encoding"
        return Response(blob, media_type="application/json", headers=headers)
    return Response(zlib.decompress(blob, wbits=31), media_type="application/json", headers=headers)


def _version(blob: bytes) -> int | None:
    """The version of a stored summary, from its first bytes."""
    try:
        start = zlib.decompressobj(wbits=31).decompress(blob, 32)
    except zlib.error:
        return None
    found = _VERSION.match(start)
    return int(found.group(1)) if found else None


def _make(service: Lab, trial: Trial) -> bytes:
    assert trial.mcap is not None
    with tempfile.TemporaryDirectory(prefix="labd-summary-") as folder:
        mcap = Path(folder) / RECORD_FILE
        service.store.copy_to(trial.mcap, mcap)  # checked against its digest
        try:
            blob = service.host.summarize(mcap, seconds=SECONDS)
        except SummaryError as err:
            message = f"the record of trial {trial.id} could not be summarized: {err}"
            raise ApiError(500, message) from None
        path = Path(folder) / SUMMARY
        path.write_bytes(blob)
        digest = service.store.put_file(path)
    service.index.put_derived(trial.id, Derived(SUMMARY, digest, len(blob), SUMMARY_MEDIA_TYPE))
    return blob
