"""The trial record, typed: what every part of the lab reads and writes about a trial.

One record goes from the queue to the index, the API, the CLI and the workers:

- ``status`` is the lifecycle only: ``queued`` → ``running`` → ``finished`` (or
  ``cancelled`` at any point before it finished);
- a finished trial has an ``outcome``, its headline: ``success`` (the task was achieved),
  ``fail`` (it ran to its end without achieving it) or ``error`` (it broke: a crash, a
  stall, a limit, a fault of the lab); with a ``reason`` a person can act on, and the
  task's ``metrics``;
- ``kind`` is ``trial`` (a controller from a repository) or ``demonstration`` (a
  person driving a live robot).

The models are pydantic, so the HTTP API serves them as they are and documents them in
its OpenAPI schema; the index builds them from its rows, the remote worker from JSON.
"""

from __future__ import annotations

import datetime as dt
from enum import StrEnum
from typing import Annotated, Any, Self

from pydantic import BaseModel, ConfigDict, Field, model_validator

MAX_SEED = 2**63 - 1
# The largest id a row of the index can have (trials, tokens, reservations): their id
# columns are INTEGER, 32 bits on PostgreSQL; an id past it names no row anywhere.
MAX_ID = 2**31 - 1
MAX_SIZE = 2**63 - 1  # bytes: the largest size the index's BIGINT columns hold
Value = bool | int | float | str  # a task parameter's value


class Status(StrEnum):
    """Where a trial is in its life."""

    QUEUED = "queued"
    RUNNING = "running"
    FINISHED = "finished"
    CANCELLED = "cancelled"

    @property
    def ended(self) -> bool:
        return self in (Status.FINISHED, Status.CANCELLED)


class Outcome(StrEnum):
    """How a finished trial went: its headline."""

    SUCCESS = "success"  # the task was achieved
    FAIL = "fail"  # it ran to its end without achieving the task
    ERROR = "error"  # it broke: crash, stall, limit, lab fault


class Kind(StrEnum):
    TRIAL = "trial"  # a controller from a repository
    DEMONSTRATION = "demonstration"  # a person driving a live robot


class EpisodeStatus(StrEnum):
    """Where a trial's episode is, as its task tells it: what ``/lab/episode`` says each
    tick, and so what its record holds. Not the trial's ``Status``: an episode that
    ended (succeeded, failed, truncated at its time limit) leaves the trial to be judged
    (``scheduler.outcome``)."""

    RUNNING = "running"
    SUCCEEDED = "succeeded"
    FAILED = "failed"
    TRUNCATED = "truncated"  # its time limit was reached

    @property
    def ended(self) -> bool:
        return self is not EpisodeStatus.RUNNING


Seed = Annotated[int, Field(ge=0, le=MAX_SEED, description="the episode's seed")]


class TrialRequest(BaseModel):
    """What to run: a repository at a ref, a task, its parameters and a seed.

    The fields are checked here once; the task and its parameters against the lab's
    tasks when the request is submitted.
    """

    model_config = ConfigDict(extra="forbid")

    repository: str = Field(min_length=1, max_length=2048, description="a git URL or path")
    ref: str | None = Field(None, max_length=256, description="branch, tag or commit")
    task: str | None = Field(
        None,
        min_length=1,
        max_length=64,
        description="a task from /api/tasks; by default the one the repository's lab.toml names",
    )
    params: dict[str, Value] = Field(default_factory=dict, description="task parameters")
    seed: Seed = 0


class PinnedRecord(BaseModel):
    """An archived record a controller learns from, pinned when its trial was submitted.

    ``mcap`` is the record's blob (its bytes' sha256, checked whenever it is read) and
    ``data_digest`` the record's own data digest over ``digest_topics``, checked again
    before the record is put in the sandbox: a rerun gets exactly these bytes or none.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    trial: int
    kind: Kind
    task: str
    seed: int
    outcome: Outcome | None
    data_digest: str
    digest_topics: list[str]
    mcap: str
    size: int

    def manifest_entry(self) -> dict[str, Any]:
        """What the trial's manifest says of this record (part of its digest)."""
        return {"trial": self.trial, "data_digest": self.data_digest, "mcap": self.mcap}


class Ending(BaseModel):
    """How a trial ended: ``finished`` with an outcome, or ``cancelled`` without one."""

    model_config = ConfigDict(frozen=True)

    status: Status
    outcome: Outcome | None = None
    reason: str
    lab_fault: bool = Field(
        default=False,
        description="an error of the lab's making (its worker lost, its storage failed),"
        " not of the controller's: an evaluation with such an episode is partial",
    )

    @model_validator(mode="after")
    def _consistent(self) -> Self:
        if self.status is Status.FINISHED and self.outcome is None:
            raise ValueError("a finished trial has an outcome")
        if self.lab_fault and self.outcome is not Outcome.ERROR:
            raise ValueError("only an error is the lab's fault")
        if self.status is Status.CANCELLED and self.outcome is not None:
            raise ValueError("a cancelled trial has no outcome")
        if not self.status.ended:
            raise ValueError("an ending is finished or cancelled")
        return self

    @classmethod
    def success(cls, reason: str) -> Self:
        return cls(status=Status.FINISHED, outcome=Outcome.SUCCESS, reason=reason)

    @classmethod
    def fail(cls, reason: str) -> Self:
        return cls(status=Status.FINISHED, outcome=Outcome.FAIL, reason=reason)

    @classmethod
    def error(cls, reason: str) -> Self:
        return cls(status=Status.FINISHED, outcome=Outcome.ERROR, reason=reason)

    @classmethod
    def lab_error(cls, reason: str) -> Self:
        """An error the lab made, not the controller (``lab_fault``)."""
        return cls(status=Status.FINISHED, outcome=Outcome.ERROR, reason=reason, lab_fault=True)

    @classmethod
    def cancelled(cls, reason: str) -> Self:
        return cls(status=Status.CANCELLED, reason=reason)


class Filing(Ending):
    """What a worker files for a trial it ran: how it ended and what came out.

    Blobs (``mcap``, ``stdout``, ``stderr``) are digests in the content-addressed store.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    manifest: dict[str, Any] | None = None
    manifest_digest: str | None = None
    data_digest: str | None = None
    digest_topics: list[str] | None = None
    metrics: dict[str, Any] | None = None
    backend: str | None = None
    wall_seconds: float | None = None
    mcap: str | None = None
    mcap_size: int | None = Field(None, ge=0, le=MAX_SIZE)
    stdout: str | None = None
    stderr: str | None = None
    reproduced: bool | None = None  # reruns only: an identical data digest
    divergence: str | None = None  # reruns that did not reproduce: where they parted


class Trial(BaseModel):
    """A trial's whole record, as the index keeps it."""

    model_config = ConfigDict(frozen=True)

    id: int
    kind: Kind = Kind.TRIAL
    # what was asked
    repository: str
    ref: str | None
    commit: str
    task: str
    params: dict[str, Value]
    seed: int
    submitter: str
    public: bool
    rerun_of: int | None
    data: list[PinnedRecord] | None = None  # the archived records it learns from
    # where it is
    status: Status
    outcome: Outcome | None
    reason: str
    lab_fault: bool = False  # an error of the lab's making (Ending.lab_fault)
    created: dt.datetime
    started: dt.datetime | None
    finished: dt.datetime | None
    worker: str | None
    attempts: int
    cancel_requested: bool
    # what came out
    manifest: dict[str, Any] | None
    manifest_digest: str | None
    data_digest: str | None
    digest_topics: list[str] | None
    metrics: dict[str, Any] | None
    backend: str | None
    wall_seconds: float | None
    mcap: str | None
    mcap_size: int | None
    stdout: str | None
    stderr: str | None
    reproduced: bool | None
    divergence: str | None
    signature: dict[str, Any] | None = None  # the lab's, over the filed record

    @property
    def original(self) -> int:
        """The trial this one reruns, or its own id."""
        return self.rerun_of if self.rerun_of is not None else self.id

    @property
    def verdict(self) -> str | None:
        """A rerun's verdict in words: "reproduced", "diverged at ...", or None."""
        if self.rerun_of is None or self.status is not Status.FINISHED:
            return None
        if self.reproduced:
            return "reproduced"
        return self.divergence or "not compared"

    @property
    def reward(self) -> float | None:
        """The task's reward metric, if it reports one."""
        value = (self.metrics or {}).get("reward")
        return float(value) if isinstance(value, int | float) else None


class Claim(BaseModel):
    """A trial a worker holds, with what it needs to run it."""

    model_config = ConfigDict(frozen=True)

    id: int
    repository: str
    commit: str
    task: str
    params: dict[str, Value]
    seed: int
    rerun_of: int | None
    attempt: int
    data: list[PinnedRecord] | None = None
    blind: bool = Field(
        default=False,
        description="an episode of a held-out suite (or a rerun of one): its controller is"
        " told nothing of the seed, neither in its environment nor on /lab/episode",
    )
