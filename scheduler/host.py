"""The lab side of a trial, as the scheduler sees it: a small protocol that labd implements.

The scheduler runs controllers in sandboxes and files what came out; it never builds a
robot, a bridge or a recorder itself. A ``TrialHost`` (``labd.trial.LabHost``) checks
tasks and their parameters, opens the lab side of one trial, and compares records; a
``TrialLab`` is that one trial: the task in lockstep (or on the wall clock), a bridge
session private to the trial on a unix socket, and a recorder, with what the runner
needs to watch it and judge it. So imports follow the data flow: ``labd`` passes a host
in, ``scheduler`` never imports ``labd``.

The runner says once what it set up (``TrialSetup``: the task, its values and seed, the
code and what was installed for it); the lab adds what only it knows (the task's
version, the compiled model's digest, the simulator's versions) and hands back the
trial's whole manifest (``TrialLab.manifest``), which it records from ``start`` on.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

from repository.benchmark import Benchmark
from repository.evaluation import Suite
from repository.manifest import Code, Controller, Manifest, Team
from repository.trial import EpisodeStatus, PinnedRecord, Value

Attachments = Mapping[str, tuple[str, bytes]]  # name -> (media type, bytes)


@dataclass(frozen=True)
class RecordFacts:
    """What a record's file holds of what a filing (or a signature) says of it, read from
    the file: never taken from whoever offers it."""

    manifest: dict[str, Any] | None  # the manifest metadata record
    data_digest: str  # over the topics asked for, recomputed
    outcome: dict[str, Any] | None  # the ``OUTCOME`` attachment (repository.well_known), parsed
    attachments: dict[str, str]  # name -> sha256:HEX of its bytes


@dataclass(frozen=True)
class Replayed:
    """What replaying a filed record gave: its verdict (JSON), and a video of its camera
    when one was asked for."""

    verdict: bytes  # {"verified", "ticks", "compared", "divergence", "said", "video"}
    verified: bool
    video: Path | None


@dataclass(frozen=True)
class Episode:
    """The episode of a trial at one moment, as the task tells it."""

    tick: int
    running: bool
    status: EpisodeStatus  # the task's word
    reason: str
    achieved: bool  # the task was achieved
    diverged: bool  # the physics blew up: the lab's model broke, not the controller


@dataclass(frozen=True)
class TrialSetup:
    """What the runner asks of the lab for one trial, said once: the task, its full
    parameter values and seed, whether its controller is told the seed (``blind``: not)
    and runs on the wall clock (``controller.realtime``), and what the manifest says of
    the code that drives it (``code``, ``controller``, the sandbox ``runtime``, the
    archived records it learns from). ``interfaces`` are the repository's own interface
    files (path in the repository -> text): their types exist in this trial's graph
    alone."""

    task: str
    values: Mapping[str, Value]
    seed: int
    code: Code
    controller: Controller
    runtime: str
    data: Sequence[PinnedRecord] = ()
    blind: bool = False
    interfaces: Mapping[str, str] = field(default_factory=dict)


@dataclass(frozen=True)
class MatchSetup:
    """What the runner asks of the lab for one leg of a match: the task, its values
    and seed, and each side's team (side -> code and controller, in the task's order of
    sides), every one in the sandbox ``runtime``. Teams bring no interfaces of their
    own and never run on the wall clock."""

    task: str
    values: Mapping[str, Value]
    seed: int
    runtime: str
    teams: Mapping[str, Team]


class TrialLab(Protocol):
    """The lab side of one trial, from ``TrialHost.open`` to ``finish``."""

    @property
    def manifest(self) -> Manifest:
        """What runs: the setup's, with the task's version, the compiled model's digest
        and the simulator's versions (``Manifest.trial``)."""
        ...

    @property
    def digest_topics(self) -> Sequence[str]:
        """The topics the data digest covers (the task's observations and commands)."""
        ...

    async def start(self, socket: Path) -> None:
        """Listen on ``socket``, record from now on (the manifest first), publish tick 0;
        on the wall clock, start stepping. ``TrialError`` if the record cannot be written
        (a full disk)."""
        ...

    def episode(self) -> Episode: ...

    @property
    def first_tick_at(self) -> float | None:
        """The event loop's time of the first step (tick 1); None before it."""
        ...

    @property
    def last_tick_at(self) -> float | None:
        """The event loop's time of the newest step; None before the first."""
        ...

    async def ended(self) -> None:
        """Return once the episode is no longer running (at once if it is not)."""
        ...

    def metrics(self) -> dict[str, Any]: ...

    def model_files(self) -> dict[str, tuple[str, bytes]]:
        """The compiled model and its assets, for the record's attachments."""
        ...

    async def finish(self, attachments: Attachments) -> str:
        """Stop serving and stepping, close the record with ``attachments``; the data
        digest. Safe to call once, whatever happened before. ``TrialError`` if the record
        could not be written (a full disk): it is deleted, and everything else stopped."""
        ...


class MatchLab(Protocol):
    """The lab side of one leg of a match: a trial's, with a socket for each side and a
    step barrier between them (both sides step before the task does)."""

    @property
    def manifest(self) -> Manifest: ...

    @property
    def digest_topics(self) -> Sequence[str]: ...

    async def start(self, sockets: Mapping[str, Path]) -> None:
        """Listen on each side's socket (side -> path), record, publish tick 0."""
        ...

    def episode(self) -> Episode: ...

    @property
    def first_tick_at(self) -> float | None: ...

    @property
    def last_tick_at(self) -> float | None: ...

    def owing(self) -> list[str]:
        """The sides the next tick waits for: those that have not called ``/lab/step``
        since the last one."""
        ...

    async def ended(self) -> None: ...

    def metrics(self) -> dict[str, Any]: ...

    def model_files(self) -> dict[str, tuple[str, bytes]]: ...

    async def finish(self, attachments: Attachments) -> str: ...


class TrialHost(Protocol):
    """What the scheduler needs of the lab: tasks, trials, records."""

    def tasks(self) -> list[str]: ...

    def check(self, task: str, params: Mapping[str, Any]) -> dict[str, Value]:
        """The task's full parameter values (``InvalidRequest`` if any is wrong)."""
        ...

    def open(self, setup: TrialSetup, *, out: Path) -> TrialLab:
        """Build the lab side of the trial ``setup`` says, recording into ``out``
        (``TrialError``; a malformed or conflicting interface file is one naming its
        file and line)."""
        ...

    def benchmark(self, name: str) -> Benchmark:
        """The benchmark ``name`` of the lab's task packs (``InvalidRequest`` naming the
        known ones if there is none)."""
        ...

    def sides(self, task: str) -> Sequence[str]:
        """The sides of a task teams play (soccer's home and away), in order; none for a
        task one controller plays (``InvalidRequest`` for an unknown task)."""
        ...

    def open_match(self, setup: MatchSetup, *, out: Path) -> MatchLab:
        """Build the lab side of one leg of a match, recording into ``out`` (``TrialError``)."""
        ...

    def first_difference(self, a: Path, b: Path, topics: Sequence[str]) -> str | None:
        """Where two records part, in words; None if they hold the same data."""
        ...

    def data_digest(self, record: Path, topics: Sequence[str]) -> str:
        """The data digest of the MCAP file ``record`` over ``topics``, recomputed."""
        ...

    def read_record(self, record: Path, topics: Sequence[str]) -> RecordFacts:
        """The manifest, the data digest over ``topics`` and the outcome the MCAP file
        ``record`` holds, read within the archive's limits (``TrialError`` if it cannot
        be read as a record)."""
        ...

    def task_version(self, task: str) -> str:
        """The version of ``task`` this lab runs (``InvalidRequest`` for an unknown one)."""
        ...

    def suites(self, task: str) -> Sequence[Suite]:
        """The episode suites ``task`` declares for evaluations (``InvalidRequest`` for an
        unknown task)."""
        ...

    def digest_topics(self, task: str) -> list[str]:
        """The topics a trial of ``task``'s data digest covers, sorted."""
        ...

    def dataset(self, records: Sequence[tuple[PinnedRecord, Path]], out: Path) -> None:
        """Write the learning formats of ``records`` (checked MCAP files) under ``out``:
        a LeRobot dataset per task, one episode per record (``scheduler.data``)."""
        ...

    def summarize(self, mcap: Path, *, seconds: float) -> bytes | None:
        """The record's summary for its page (``well_known.SUMMARY``), made within ``seconds``;
        None if this lab makes none. Raises if the record cannot be summarized."""
        ...

    def replay(self, mcap: Path, out: Path, *, seconds: float | None = None) -> Replayed | None:
        """Re-simulate a filed record from its actions and compare it with what it holds,
        within ``seconds``: the verdict, with no video; None if this lab
        does not replay. A record that cannot be replayed is a verdict that says why,
        not an exception."""
        ...
