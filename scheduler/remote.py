"""A worker on another machine: the queue and the blob store through a lab's HTTP API.

``labd worker --server URL --token TOKEN`` runs the same ``Worker`` as ``labd serve``
does, with this in place of the database and the store. The token must be a worker's
(``labd users add NAME --worker``). The worker fetches repositories itself, with its
own mirror cache and its own credentials; what it uploads is checked against its
digest by the server before it is stored.

Every request names the worker protocol it speaks (``PROTOCOL_HEADER``); a lab that
speaks another refuses it with a message naming both versions, so a worker left at an
old version never files records the new lab would misread.
"""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path

from pydantic import BaseModel, ConfigDict, Field

from repository.index import Derived
from repository.trial import MAX_SIZE, Claim, Filing, Trial
from scheduler.canary import Health
from scheduler.client import ApiClient, version
from scheduler.errors import ApiRefused, FilingRefused, RemoteError
from scheduler.states import State

PROTOCOL = 5  # 1: labd 0.1 (status succeeded/failed); 2: status and outcome apart;
# 3: the lab holds a filing to its record (422 if not borne out), no metrics without one;
# 4: claims say ``blind`` (held-out episodes: the controller learns no seed), replay
# verdicts are the lab's own (a remote worker files none); hello's ``git`` (the prefix
# the lab records its hosted repositories under) came later, an addition a worker of 4
# ignores; 5: a claim carries the trial's order whole ({"id", "attempt", "order":
# {repository, ref, commit, task, params, seed, public, kind, rerun_of, data}, "blind"}),
# where a claim of 4 had some of its fields beside id and attempt: a worker of 4 would
# read a claim of 5 as missing them
PROTOCOL_HEADER = "X-Labd-Worker-Protocol"
VERSION_HEADER = "X-Labd-Version"


class RemoteLab:
    """``Jobs`` and ``Blobs`` (``scheduler.worker``) over a lab's HTTP API."""

    def __init__(self, server: str, token: str, *, timeout: float = 60.0) -> None:
        self.api = ApiClient(
            server,
            token,
            timeout=timeout,
            headers={PROTOCOL_HEADER: str(PROTOCOL), VERSION_HEADER: version()},
        )
        self.server = self.api.server
        self.replays = False  # whether the lab takes this worker's replays (``hello``)
        self.git: str | None = None  # where the lab records its hosted repositories (``hello``)

    def close(self) -> None:
        self.api.close()

    def hello(self) -> str:
        """Check the token and that the lab speaks this worker protocol; the lab's version
        (``ApiRefused`` with the lab's explanation if not). ``replays`` says after it
        whether the lab takes this worker's replay verdicts (only from its own workers:
        it replays what others file itself), ``git`` the URL its hosted repositories are
        recorded under (``PUBLIC/git``; None from a lab that does not say)."""
        reply = self.api.request("GET", "/api/workers/hello").json()
        self.replays = reply.get("replays") is True
        git = reply.get("git")
        self.git = git if isinstance(git, str) and git else None
        return str(reply["version"])

    # -- Jobs -------------------------------------------------------------------------

    def claim(self, worker: str) -> Claim | None:
        response = self.api.request("POST", "/api/workers/claim", json={"worker": worker})
        if response.status_code == 204:
            return None
        return self.api.parse(response, Claim)

    def heartbeat(self, trial_id: int, worker: str) -> bool:
        path = f"/api/workers/trials/{trial_id}/heartbeat"
        return self.api.post(path, Kept, json={"worker": worker}).keep

    def finish(self, trial_id: int, worker: str, filing: Filing) -> bool:
        """File the trial; ``FilingRefused`` (the lab's words) if the lab's check of the
        filing against its record refused it (422), as ``Queue.finish`` raises it."""
        path = f"/api/workers/trials/{trial_id}/finish"
        body = {"worker": worker, "filing": filing.model_dump(mode="json")}
        try:
            return self.api.post(path, Filed, json=body).filed
        except ApiRefused as err:
            if err.status == 422:
                raise FilingRefused(trial_id, [err.message]) from None
            raise

    def report(self, health: Health) -> None:
        body = {"worker": health.worker, "state": health.state, "detail": health.detail}
        self.api.request("POST", "/api/workers/health", json=body)

    def trial(self, trial_id: int) -> Trial:
        return self.api.get(f"/api/workers/trials/{trial_id}", Trial)

    def derive(self, trial_id: int, worker: str, item: Derived) -> bool:
        path = f"/api/workers/trials/{trial_id}/derived"
        body = {"worker": worker, "item": DerivedItem(**asdict(item)).model_dump()}
        return self.api.post(path, Filed, json=body).filed

    # -- Blobs ------------------------------------------------------------------------

    def put_file(self, path: str | Path) -> str:
        return self.api.upload(Path(path))

    def copy_to(self, digest: str, dest: str | Path) -> Path:
        dest = Path(dest)
        try:
            self.api.download(f"/api/blobs/{digest}", dest, digest=digest)
        except RemoteError as err:
            raise RemoteError(f"blob {digest}: {err}") from None
        return dest


# The bodies of the workers' API, shared by this client and the lab's server.


class WorkerName(BaseModel):
    model_config = ConfigDict(extra="forbid")
    worker: str = Field(min_length=1, max_length=100)


class FinishBody(WorkerName):
    filing: Filing


class DerivedItem(BaseModel):
    """A derived artifact of a record (its blob uploaded first), e.g. a page summary."""

    model_config = ConfigDict(extra="forbid")
    name: str = Field(min_length=1, max_length=64)
    digest: str = Field(pattern=r"^sha256:[0-9a-f]{64}$")
    size: int = Field(ge=0, le=MAX_SIZE)
    media_type: str = Field(min_length=1, max_length=128)


class DeriveBody(WorkerName):
    item: DerivedItem


class HealthBody(WorkerName):
    state: State
    detail: str = Field("", max_length=2000)


class Kept(BaseModel):
    keep: bool  # false: stop (cancelled, or the lease was lost)


class Filed(BaseModel):
    filed: bool  # false: this worker no longer held the trial
