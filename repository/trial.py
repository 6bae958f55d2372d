"""The trial record, typed: what every part of the lab reads and writes about a trial.

What was asked is one ``Order``, built where a trial is asked for and passed whole: the
queue keeps it as the trial's row, a ``Claim`` hands it to a worker, the runner runs it.
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
    MATCH = "match"  # a leg of a match: two controllers, one a side each


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


class TeamRef(BaseModel):
    """The away team of a match's leg, as its order names it: the code (a repository,
    the ref asked for, the commit it resolved to). The order's own code plays home."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    repository: str = Field(description="a git URL or path")
    ref: str | None = Field(default=None, description="the branch, tag or commit asked for")
    commit: str = Field(default="", description="the commit the ref resolved to")


class Order(BaseModel):
    """What was asked of the lab for one trial: one value from the request to the record.

    The code (a repository, the ref asked for, the commit it resolved to), the task, its
    parameters and seed, whether the repository is public, the kind of trial, the trial
    it reruns and the archived records it learns from. Built once where a trial is asked
    for (a submission, an evaluation's episodes, a rerun, a live robot's drive, ``labd
    run``) and passed whole, as httpx passes its ``Request``: the queue keeps it as the
    trial's row (``Index.add_trial``), a ``Claim`` hands it to a worker, the runner runs
    it. A new thing a trial asks is one field here, not an edit at every call site.

    Two fields are open until the code is checked out, in ``labd run`` alone (the queue
    holds its orders resolved): ``commit`` ("" until the ref is resolved; a
    demonstration, which has no code, keeps "") and ``task`` (None: the one the
    repository's ``lab.toml`` names).
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    repository: str = Field(description="a git URL or path (robot:NAME for a demonstration)")
    ref: str | None = Field(default=None, description="the branch, tag or commit asked for")
    commit: str = Field(default="", description="the commit the ref resolved to")
    task: str | None = Field(default=None, description="the task; None: the one lab.toml names")
    params: dict[str, Value] = Field(default_factory=dict, description="task parameters")
    seed: int = Field(default=0, description="the episode's seed")
    public: bool = Field(
        default=False,
        description="a repository anyone may read (private unless the lab found it so)",
    )
    kind: Kind = Kind.TRIAL
    rerun_of: int | None = Field(default=None, description="the trial this one reruns")
    data: tuple[PinnedRecord, ...] = Field(
        default=(), description="the archived records it learns from, pinned when it was submitted"
    )
    away: TeamRef | None = Field(
        default=None, description="a match's leg: the team at away (this order's code is home)"
    )
    step_deadline: float | None = Field(
        default=None,
        gt=0,
        description="a match's leg: seconds a team may keep the other waiting for its step",
    )

    @model_validator(mode="after")
    def _teams(self) -> Self:
        if (self.kind is Kind.MATCH) != (self.away is not None):
            raise ValueError("a match's leg, and only a match's leg, names its away team")
        if self.step_deadline is not None and self.kind is not Kind.MATCH:
            raise ValueError("only a match's leg has a step deadline")
        return self

    def episode(self, seed: int) -> Order:
        """The same order with another seed (an evaluation's episode)."""
        return self.model_copy(update={"seed": seed})

    def rerun(self, of: int) -> Order:
        """The order of a rerun of trial ``of``, which this order queued: the same code,
        pinned at its commit, the same task, parameters, seed and records it learnt from
        (whatever was filed since), linked to it."""
        away = None if self.away is None else self.away.model_copy(update={"ref": self.away.commit})
        return self.model_copy(update={"ref": self.commit, "rerun_of": of, "away": away})


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
    # a match's leg: the team at away (the code above plays home)
    away_repository: str | None = None
    away_ref: str | None = None
    away_commit: str | None = None
    step_deadline: float | None = None
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
    def order(self) -> Order:
        """What was asked for this trial, as it was queued."""
        return Order(
            repository=self.repository,
            ref=self.ref,
            commit=self.commit,
            task=self.task,
            params=self.params,
            seed=self.seed,
            public=self.public,
            kind=self.kind,
            rerun_of=self.rerun_of,
            data=tuple(self.data or ()),
            away=self.away,
            step_deadline=self.step_deadline,
        )

    @property
    def away(self) -> TeamRef | None:
        """A match's leg: the team at away."""
        if self.away_repository is None:
            return None
        return TeamRef(
            repository=self.away_repository, ref=self.away_ref, commit=self.away_commit or ""
        )

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
    """A trial a worker holds: its id, which attempt this is, and its order whole, with
    what the worker needs to know to run it (``blind``)."""

    model_config = ConfigDict(frozen=True)

    id: int
    attempt: int
    order: Order
    blind: bool = Field(
        default=False,
        description="an episode of a held-out suite (or a rerun of one): its controller is"
        " told nothing of the seed, neither in its environment nor on /lab/episode",
    )
