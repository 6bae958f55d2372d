"""The API of workers on other machines (``labd worker --server URL``), and blobs.

    POST /api/workers/claim                        {"worker"} → a Claim, or 204
    POST /api/workers/trials/{id}/heartbeat        {"worker"} → {"keep": bool}
    POST /api/workers/trials/{id}/finish           {"worker", "filing"} → {"filed": bool}
    POST /api/workers/trials/{id}/derived          {"worker", "item"} → {"filed": bool}
    GET  /api/workers/trials/{id}                  the whole record (a rerun's original)
    PUT  /api/blobs/sha256:HEX                     the bytes; stored if they match
    GET  /api/blobs/sha256:HEX                     a blob, checked before it is sent

Workers need a worker's token (``labd users add NAME --worker``) and must speak this
lab's worker protocol (``scheduler.remote.PROTOCOL``): a worker of another version is
refused with a 409 naming both, before it can claim or file anything. A filing sets
only what a worker knows (``repository.trial.Filing``); everything else stays the
queue's. The lab reads the record a filing names before it files and signs it
(``scheduler.filing``): a filing its record does not bear out is a 422 naming each
difference, and nothing is filed or signed.
"""

from __future__ import annotations

import asyncio
import hashlib
import shutil
import tempfile
from pathlib import Path
from typing import Annotated

from fastapi import APIRouter, Depends, Header, Request, Response
from fastapi.responses import StreamingResponse
from pydantic import BaseModel

from labd import __version__
from labd.api.common import Lab, Reader, Writer, blob_response
from labd.api.errors import ApiError, Conflict, Forbidden, responses
from labd.api.models import Digest, Id
from labd.workers import LOCAL_WORKERS
from repository.index import Derived, User
from repository.trial import Claim, Trial
from repository.units import GiB, MiB
from repository.well_known import REPLAY, SUMMARY, VIDEO
from scheduler.canary import Health
from scheduler.outcome import storage_failure
from scheduler.remote import (
    PROTOCOL,
    PROTOCOL_HEADER,
    VERSION_HEADER,
    DeriveBody,
    Filed,
    FinishBody,
    HealthBody,
    Kept,
    WorkerName,
)

MAX_BLOB = 4 * GiB
WRITE_BATCH = 4 * MiB  # bytes of an upload written and hashed at once, on a thread
WORKER_MADE = frozenset({SUMMARY, REPLAY, VIDEO})  # what a worker may file beside a record


class Stored(BaseModel):
    digest: str  # sha256:HEX


def _protocol(
    protocol: Annotated[str | None, Header(alias=PROTOCOL_HEADER)] = None,
    version: Annotated[str | None, Header(alias=VERSION_HEADER)] = None,
) -> None:
    if protocol == str(PROTOCOL):
        return
    theirs = f"labd {version}" if version else "a labd older than 0.2"
    spoken = f"worker protocol {protocol}" if protocol else "no worker protocol"
    raise Conflict(
        f"this worker is {theirs} and speaks {spoken}; this lab is labd {__version__}"
        f" and speaks worker protocol {PROTOCOL}: run the same version of labd on both"
    )


def _worker(user: Writer) -> User:
    if not user.worker:
        raise Forbidden(f"{user.name} is not a worker (labd users add NAME --worker)")
    return user


WorkerUser = Annotated[User, Depends(_worker)]
router = APIRouter(
    tags=["workers"],
    dependencies=[Depends(_protocol)],
    responses=responses(401, 403, 409),
)


class Hello(BaseModel):
    version: str  # the lab's labd
    protocol: int  # the worker protocol it speaks
    worker: str  # the user the token belongs to
    replays: bool  # whether the lab takes this worker's replay verdicts (its own workers')
    # the prefix its hosted repositories are recorded under (PUBLIC/git), None before it
    # serves: a worker fetches those from its own --server (its public URL may not lead there)
    git: str | None = None


def _own(user: User) -> bool:
    """The lab's own worker processes (``labd.workers``), whose replays it takes; of a
    worker elsewhere, the lab replays what it files itself (``labd.replays``)."""
    return user.name == LOCAL_WORKERS


@router.get("/api/workers/hello")
def hello(user: WorkerUser, service: Lab) -> Hello:
    """A worker checks its token and version before it claims anything, and learns
    whether to replay what it files (only the lab's own workers do) and under which URL
    the lab records its hosted repositories."""
    return Hello(
        version=__version__,
        protocol=PROTOCOL,
        worker=user.name,
        replays=_own(user),
        git=service.git_url,
    )


def _named(user: User, name: str) -> str:
    """Workers' names carry their user's, so one worker token cannot act for another."""
    return f"{user.name}@{name}"


@router.post(
    "/api/workers/claim",
    response_model=Claim,
    responses={204: {"description": "nothing to run now"}},
)
def claim(body: WorkerName, service: Lab, user: WorkerUser) -> Claim | Response:
    """The next trial for this worker, under a lease; 204 when there is none."""
    got = service.queue.claim(_named(user, body.worker))
    if got is None:
        return Response(status_code=204)
    return got


@router.post("/api/workers/trials/{trial_id}/heartbeat")
def heartbeat(trial_id: Id, body: WorkerName, service: Lab, user: WorkerUser) -> Kept:
    """Renew the lease; ``keep`` false means stop (cancelled, or the lease was lost)."""
    return Kept(keep=service.queue.heartbeat(trial_id, _named(user, body.worker)))


@router.post("/api/workers/trials/{trial_id}/finish", responses=responses(422))
def finish(trial_id: Id, body: FinishBody, service: Lab, user: WorkerUser) -> Filed:
    """File a trial's ending, held to the record it names first (422 if the record says
    otherwise: nothing filed, nothing signed); ``filed`` false if this worker no longer
    held it."""
    filing = body.filing
    for key in ("mcap", "stdout", "stderr"):
        digest = getattr(filing, key)
        if digest and not service.store.exists(digest):
            raise ApiError(422, f"filing.{key}: upload {digest} first")
    return Filed(filed=service.queue.finish(trial_id, _named(user, body.worker), filing))


@router.post("/api/workers/trials/{trial_id}/derived", responses=responses(404, 422))
def derived(trial_id: Id, body: DeriveBody, service: Lab, user: WorkerUser) -> Filed:
    """Keep what a worker made of a trial it filed (its page summary, its replay's verdict
    and video), the blob uploaded first and checked against its digest; ``filed`` false
    if the trial is not this worker's."""
    item = body.item
    if item.name not in WORKER_MADE:
        made = ", ".join(sorted(WORKER_MADE))
        raise ApiError(422, f"item.name: a worker files {made}, not {item.name!r}")
    if item.name == REPLAY and not _own(user):
        raise ApiError(
            422,
            f"item.name: {REPLAY} is the lab's own word: it replays what {user.name} filed"
            " itself (a worker elsewhere files no replay verdict)",
        )
    if not service.store.exists(item.digest):
        raise ApiError(422, f"item.digest: upload {item.digest} first")
    if service.store.size(item.digest) != item.size:
        raise ApiError(422, f"item.size: the blob {item.digest} is not {item.size} bytes")
    derived = Derived(item.name, item.digest, item.size, item.media_type)
    return Filed(filed=service.queue.derive(trial_id, _named(user, body.worker), derived))


@router.post("/api/workers/health", status_code=204, response_class=Response)
def health(body: HealthBody, service: Lab, user: WorkerUser) -> Response:
    """A worker says how its canaries went: ``out`` takes it out of the pool (it says so)."""
    service.queue.report(Health(_named(user, body.worker), body.state, body.detail))
    return Response(status_code=204)


@router.get("/api/workers/trials/{trial_id}", responses=responses(404))
def record(trial_id: Id, service: Lab, user: WorkerUser) -> Trial:
    """A trial's whole record, as the index keeps it (a worker compares a rerun with it)."""
    return service.index.trial(trial_id)


@router.put("/api/blobs/{digest}", status_code=201, responses=responses(413, 422, 507))
async def put_blob(digest: Digest, request: Request, service: Lab, user: WorkerUser) -> Stored:
    """Store the body under ``digest``, if it is what the body hashes to."""
    try:
        return await _store(digest, request, service)
    except OSError as err:  # the lab's disk is full: the worker files the trial as an error
        raise ApiError(507, storage_failure(err, "the lab could not store the blob")) from err


async def _store(digest: str, request: Request, service: Lab) -> Stored:
    """Stream the body to a file and hash it as it comes, then store the file: the disk
    and the hashing work on threads, in batches, so that the server's loop keeps taking
    other requests during an upload of gigabytes."""
    folder = Path(await asyncio.to_thread(tempfile.mkdtemp, prefix="labd-upload-"))
    try:
        upload = await asyncio.to_thread(_Upload, folder / "blob")
        try:
            batch: list[bytes] = []
            waiting = 0
            async for chunk in request.stream():
                if upload.size + waiting + len(chunk) > MAX_BLOB:
                    raise ApiError(413, f"a blob may be at most {MAX_BLOB // GiB} GiB")
                batch.append(chunk)
                waiting += len(chunk)
                if waiting >= WRITE_BATCH:
                    await asyncio.to_thread(upload.write, batch)
                    batch, waiting = [], 0
            await asyncio.to_thread(upload.write, batch)
        finally:
            await asyncio.to_thread(upload.close)
        actual = f"sha256:{upload.sha.hexdigest()}"
        if actual != digest:
            raise ApiError(422, f"the body hashes to {actual}, not {digest}")
        stored = await asyncio.to_thread(service.store.put_file, upload.path)
    finally:
        await asyncio.to_thread(shutil.rmtree, folder, True)
    return Stored(digest=stored)


class _Upload:
    """A blob being uploaded: its file, its hash and its size so far (used from one
    thread at a time)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.sha = hashlib.sha256()
        self.size = 0
        self._out = path.open("wb")

    def write(self, chunks: list[bytes]) -> None:
        for chunk in chunks:
            self.sha.update(chunk)
            self._out.write(chunk)
            self.size += len(chunk)

    def close(self) -> None:
        self._out.close()


blobs = APIRouter(tags=["data"])


@blobs.get(
    "/api/blobs/{digest}",
    response_class=StreamingResponse,
    responses={200: {"content": {"application/octet-stream": {}}}, **responses(401, 404, 500)},
)
def get_blob(digest: Digest, service: Lab, reader: Reader) -> StreamingResponse:
    """A blob of the archive, checked before it is sent: the record, a log or a derived
    artifact of a trial the caller may read (a held-out episode's are nobody's but the
    operator's until its suite is retired), or what a trial a worker holds needs. Any
    other digest is not found, whether or not the store has it."""
    worker = reader.name if reader is not None and reader.worker else None
    if not service.index.blob_readable(digest, worker):  # before the store is asked
        raise ApiError(404, f"{digest}: no record, log or artifact you may read has this digest")
    return blob_response(service, digest, "application/octet-stream", None)
