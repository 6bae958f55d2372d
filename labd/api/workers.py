"""The API of workers on other machines (``labd worker --server URL``), and blobs.

    POST /api/workers/claim                        {"worker"} → a trial, or 204
    POST /api/workers/trials/{id}/heartbeat        {"worker"} → {"keep": bool}
    POST /api/workers/trials/{id}/finish           {"worker", "record"} → {"filed": bool}
    PUT  /api/blobs/sha256:HEX                     the bytes; stored if they match
    GET  /api/blobs/sha256:HEX                     a blob, checked before it is sent

Workers need a worker's token (``labd users add NAME --worker``). A finished record
may set only the columns a worker fills; everything else stays the queue's.
"""

from __future__ import annotations

import dataclasses
import hashlib
import tempfile
from pathlib import Path
from typing import Annotated, Any

from fastapi import APIRouter, Depends, Request, Response
from fastapi.responses import StreamingResponse
from pydantic import BaseModel, ConfigDict, Field

from labd.api.common import ApiError, Lab, Writer, blob_response
from repository.errors import ArchiveError
from repository.index import User

router = APIRouter(tags=["workers"])
FILED = frozenset(
    {
        "status",
        "reason",
        "manifest",
        "manifest_digest",
        "data_digest",
        "digest_topics",
        "metrics",
        "backend",
        "wall_seconds",
        "mcap",
        "mcap_size",
        "stdout",
        "stderr",
        "reproduced",
        "divergence",
    }
)
MAX_BLOB = 4 << 30


def _worker(user: Writer) -> User:
    if not user.worker:
        raise ApiError(403, f"{user.name} is not a worker (labd users add NAME --worker)")
    return user


WorkerUser = Annotated[User, Depends(_worker)]


class WorkerName(BaseModel):
    model_config = ConfigDict(extra="forbid")
    worker: str = Field(min_length=1, max_length=100)


class Finished(WorkerName):
    record: dict[str, Any]


def _named(user: User, name: str) -> str:
    """Workers' names carry their user's, so one worker token cannot act for another."""
    return f"{user.name}@{name}"


@router.post("/api/workers/claim", response_model=None)
def claim(body: WorkerName, service: Lab, user: WorkerUser) -> dict[str, Any] | Response:
    """The next trial for this worker, under a lease; 204 when there is none."""
    got = service.queue.claim(_named(user, body.worker))
    if got is None:
        return Response(status_code=204)
    return dataclasses.asdict(got)


@router.post("/api/workers/trials/{trial_id}/heartbeat")
def heartbeat(trial_id: int, body: WorkerName, service: Lab, user: WorkerUser) -> dict[str, bool]:
    """Renew the lease; ``keep`` false means stop (cancelled, or the lease was lost)."""
    return {"keep": service.queue.heartbeat(trial_id, _named(user, body.worker))}


@router.post("/api/workers/trials/{trial_id}/finish")
def finish(trial_id: int, body: Finished, service: Lab, user: WorkerUser) -> dict[str, bool]:
    """File a trial's outcome; ``filed`` false if this worker no longer held it."""
    unknown = sorted(set(body.record) - FILED)
    if unknown:
        raise ApiError(422, f"record: a worker does not set {', '.join(unknown)}")
    if body.record.get("status") not in ("succeeded", "failed", "cancelled"):
        raise ApiError(422, "record.status: succeeded, failed or cancelled")
    for key in ("mcap", "stdout", "stderr"):
        if body.record.get(key) and not service.store.exists(body.record[key]):
            raise ApiError(422, f"record.{key}: upload {body.record[key]} first")
    filed = service.queue.finish(trial_id, _named(user, body.worker), **body.record)
    return {"filed": filed}


@router.put("/api/blobs/{digest}", status_code=201)
async def put_blob(digest: str, request: Request, service: Lab, user: WorkerUser) -> dict[str, str]:
    """Store the body under ``digest``, if it is what the body hashes to."""
    sha = hashlib.sha256()
    size = 0
    with tempfile.TemporaryDirectory(prefix="labd-upload-") as folder:
        path = Path(folder) / "blob"
        with path.open("wb") as out:
            async for chunk in request.stream():
                size += len(chunk)
                if size > MAX_BLOB:
                    raise ApiError(413, f"a blob may be at most {MAX_BLOB >> 30} GiB")
                sha.update(chunk)
                out.write(chunk)
        actual = f"sha256:{sha.hexdigest()}"
        if actual != digest:
            raise ApiError(422, f"the body hashes to {actual}, not {digest}")
        try:
            stored = service.store.put_file(path)
        except ArchiveError as err:
            raise ApiError(422, str(err)) from None
    return {"digest": stored}


@router.get("/api/blobs/{digest}", tags=["data"])
def get_blob(digest: str, service: Lab) -> StreamingResponse:
    """A blob of the archive (records and logs are public), checked before it is sent."""
    return blob_response(service, digest, "application/octet-stream", None)
