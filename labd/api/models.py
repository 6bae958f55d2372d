"""The bodies of the HTTP API: what a person, a script and the ``labd`` CLI read.

Every 2xx body is one of these models (so ``/openapi.json`` describes it), built from
the archive's typed record (``repository.trial.Trial``); every error is ``ErrorBody``.
A trial's headline is its outcome: ``success``, ``fail`` or ``error`` once finished.

The bodies a client reads back (trials, the lab's status, evaluations, reservations)
are here rather than beside their routes, and this module imports only the light
vocabulary of the archive and the scheduler: the ``labd`` commands that talk to a lab
import it without FastAPI, SQLAlchemy or the simulator.
"""

from __future__ import annotations

import datetime as dt
from collections.abc import Collection
from typing import TYPE_CHECKING, Annotated, Any

from pydantic import BaseModel, Field, StringConstraints

from labd.sim import registry
from repository.evaluation import Evaluation, SuiteInfo
from repository.slots import State as SlotState
from repository.trial import MAX_ID, Kind, Outcome, PinnedRecord, Status, TeamRef, Trial, Value
from scheduler.states import Cancel, Stage, State

if TYPE_CHECKING:
    from repository.index import CommitPage

# What a client names a record by, checked where it comes in: an id past the index's
# range, or a digest that is not one, is a 422 saying so, never a query that fails.
Id = Annotated[
    int, Field(ge=1, le=MAX_ID, description=f"an id of the archive's index (1 to {MAX_ID})")
]
Digest = Annotated[
    str,
    StringConstraints(pattern=r"^sha256:[0-9a-f]{64}$"),
    Field(description="a blob's name: sha256: and the 64 lowercase hex digits of its bytes"),
]


class ErrorBody(BaseModel):
    """Every error the API sends: what went wrong and what to do about it."""

    error: str = Field(description="a sentence a person can act on")


class Blob(BaseModel):
    """A file of the archive: its digest, size and where to download it."""

    digest: str = Field(description="sha256:HEX of its bytes")
    size: int | None
    url: str


class TrialSummary(BaseModel):
    """A trial as lists show it: its outcome first, what ran, what came out."""

    id: int
    kind: Kind
    status: Status = Field(description="queued, running, finished or cancelled")
    outcome: Outcome | None = Field(description="success, fail or error, once finished")
    reason: str = Field(description="why it ended as it did, or where it is")
    reward: float | None = Field(description="the task's reward metric, if it has one")
    repository: str
    ref: str | None
    commit: str
    task: str
    params: dict[str, Value]
    seed: int
    submitter: str
    public: bool
    rerun_of: int | None
    away: TeamRef | None = Field(
        None, description="a match's leg: the team that played away (the code above: home)"
    )
    step_deadline: float | None = Field(
        None, description="a match's leg: seconds a team may keep the other waiting for its step"
    )
    verdict: str | None = Field(description="a rerun's: reproduced, or where it diverged")
    reproduced: bool | None
    divergence: str | None
    attempts: int
    created: dt.datetime
    started: dt.datetime | None
    finished: dt.datetime | None
    manifest_digest: str | None
    data_digest: str | None
    metrics: dict[str, Any] | None
    backend: str | None
    wall_seconds: float | None
    url: str = Field(description="this record in the API")
    page: str = Field(description="this trial's web page")
    mcap: Blob | None = Field(description="the MCAP record")
    logs: dict[str, str] = Field(description="the controller's stdout and stderr, by URL")


class TrialDetail(TrialSummary):
    """One trial in full: with its manifest and who runs it."""

    manifest: dict[str, Any] | None
    data: list[PinnedRecord] | None = Field(
        None, description="the archived records it learns from, pinned when it was submitted"
    )
    digest_topics: list[str] | None
    worker: str | None
    cancel_requested: bool = Field(description="its worker has been asked to stop it")
    queued_ahead: int | None = Field(
        None,
        description="while it is queued: trials submitted before it that still wait (the"
        " queue takes turns between submitters, so it may start sooner)",
    )
    signature: dict[str, Any] | None = Field(
        description="the lab's signature of the filed record: statement, key id, signature"
    )


class CancelView(BaseModel):
    """What cancelling did, and the trial after it."""

    done: Cancel = Field(description="cancelled (it was queued), stopping (it runs) or ended")
    trial: TrialDetail


class Health(BaseModel):
    """``/healthz``: the process answers (ok); ``/readyz``: its index, blob store and
    workers answer (ready), each check saying what it found (``labd.health``)."""

    status: str
    checks: dict[str, str] = Field(
        default_factory=dict, description="/readyz: index, store, workers: what each found"
    )


class Keys(BaseModel):
    """The lab's public keys (PEM) by id; ``current`` signs new records."""

    current: str
    keys: dict[str, str]


class TrialPage(BaseModel):
    trials: list[TrialSummary]
    next: int | None = Field(description="pass as `before` for the next page; null at the end")


class CommitTrial(TrialSummary):
    reruns: list[TrialSummary]


class CommitView(BaseModel):
    """A commit's trials, newest first, each with its reruns and their verdicts."""

    commit: str
    repositories: list[str]
    trials: list[CommitTrial]
    rerun_counts: dict[str, int] = Field(description="reproduced, diverged, pending")
    truncated: bool


class Param(BaseModel):
    type: str
    default: Value
    doc: str
    minimum: float | None
    maximum: float | None
    choices: list[Value] | None
    describe: str


class TaskView(BaseModel):
    name: str
    version: str
    doc: str
    params: dict[str, Param]
    suites: list[SuiteInfo] = Field(description="its episode suites, for evaluations")


class TaskProblem(BaseModel):
    """A task plugin the lab left out, and why (``labd.sim.registry``)."""

    plugin: str = Field(description="its entry point, NAME = module:attribute")
    problem: str


class TaskList(BaseModel):
    tasks: list[TaskView]
    problems: list[TaskProblem] = Field(
        default_factory=list, description="task plugins that are installed but left out"
    )


def task_list() -> TaskList:
    """Every task this lab runs, and the plugins it left out."""
    return TaskList(
        tasks=[task_view(name) for name in registry.names()],
        problems=[TaskProblem(plugin=p, problem=why) for p, why in registry.problems().items()],
    )


class WorkerView(BaseModel):
    """A worker with a trial: which, since when, and (for the lab's own) at what stage."""

    worker: str
    trial: int
    task: str
    started: dt.datetime | None
    running_seconds: float | None
    stage: Stage | None = Field(None, description="what its worker does with the trial")
    stage_seconds: float | None = None


class WorkerHealth(BaseModel):
    """What a worker last said of itself: ``out`` if a canary did not reproduce."""

    worker: str
    state: State = Field(description="ok, checking (rerunning its canaries) or out (of the pool)")
    detail: str
    since: dt.datetime


class LabStatus(BaseModel):
    """The lab right now: its version, the queue, what each busy worker runs, and the
    health of every worker that reported (its canary reruns)."""

    version: str
    queued: int
    running: list[WorkerView]
    local_workers: int
    workers: list[WorkerHealth]


class EvaluationView(Evaluation):
    """An evaluation, with where to find it."""

    url: str = Field(description="this evaluation in the API")
    page: str = Field(description="its web page")


class EvaluationPage(BaseModel):
    evaluations: list[EvaluationView]
    next: int | None = Field(description="`before` for the next page; null on the last")


class ReservationView(BaseModel):
    """A booked slot: who, which robot, when. Never its key."""

    id: int
    robot: str
    user: str
    start: dt.datetime
    end: dt.datetime = Field(description="when it ends, after any release")
    booked_end: dt.datetime = Field(description="the end as booked or extended")
    created: dt.datetime
    released: dt.datetime | None
    state: SlotState = Field(description="upcoming, current, ended or released")
    minutes: float
    calendar: str = Field(description="the robot's calendar page")


class ReservationList(BaseModel):
    reservations: list[ReservationView]


class KeyView(BaseModel):
    """A slot's key: it opens ``robot`` from the slot's start to its end."""

    key: str = Field(description='present it in the first frame, {"op": "auth", "key": ...}')
    robot: str
    path: str = Field(description="the robot's path on the lab's bridge, /robots/NAME")
    seconds: float = Field(description="seconds left in the slot now (0 before it starts)")
    reservation: ReservationView


class Booked(BaseModel):
    """A new reservation and its key."""

    reservation: ReservationView
    key: KeyView


def summary(trial: Trial, base: str) -> dict[str, Any]:
    """The fields of ``TrialSummary`` for ``trial``, with links under ``base``."""
    link = f"{base}/api/trials/{trial.id}"
    return {
        **trial.model_dump(
            exclude={
                "mcap",
                "mcap_size",
                "stdout",
                "stderr",
                "away_repository",
                "away_ref",
                "away_commit",
            }
        ),
        "away": trial.away,
        "reward": trial.reward,
        "verdict": trial.verdict,
        "url": link,
        "page": f"{base}/trials/{trial.id}",
        "mcap": (
            Blob(digest=trial.mcap, size=trial.mcap_size, url=f"{link}/data.mcap")
            if trial.mcap
            else None
        ),
        "logs": {
            stream: f"{link}/logs/{stream}"
            for stream in ("stdout", "stderr")
            if getattr(trial, stream)
        },
    }


def trial_summary(trial: Trial, base: str) -> TrialSummary:
    return TrialSummary.model_validate(summary(trial, base))


def trial_detail(trial: Trial, base: str) -> TrialDetail:
    return TrialDetail.model_validate(summary(trial, base))


def commit_view(page: CommitPage, base: str) -> CommitView:
    return CommitView(
        commit=page.commit,
        repositories=page.repositories,
        trials=[
            CommitTrial.model_validate(
                {
                    **summary(row, base),
                    "reruns": [trial_summary(r, base) for r in page.reruns.get(row.id, [])],
                }
            )
            for row in page.trials
        ],
        rerun_counts=page.rerun_counts,
        truncated=page.truncated,
    )


def task_view(name: str, retired: Collection[tuple[str, int]] = ()) -> TaskView:
    """Task ``name`` as the API shows it; ``retired`` are its retired suite versions."""
    spec = registry.get(name)
    return TaskView(
        name=spec.name,
        version=spec.version,
        doc=spec.doc,
        suites=[
            SuiteInfo(
                name=suite.name,
                version=suite.version,
                episodes=suite.episodes,
                held_out=suite.held_out,
                retired=(suite.name, suite.version) in retired,
                seeds=None if suite.held_out else list(suite.seeds),
                params=dict(suite.params),
                doc=suite.doc,
            )
            for suite in spec.suites
        ],
        params={
            p.name: Param(
                type=p.kind.__name__,
                default=p.default,
                doc=p.doc,
                minimum=p.minimum,
                maximum=p.maximum,
                choices=list(p.choices) or None,
                describe=p.describe(),
            )
            for p in spec.params.declared.values()
        },
    )
