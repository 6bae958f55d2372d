"""The lab side of a batch trial: what ``scheduler.host`` asks of labd.

``LabHost`` is the ``TrialHost`` a runner is given (by ``labd run``, by the service's
workers, by ``labd worker``): it checks tasks and parameters against the registry,
opens ``LabTrial``\\ s, compares records and summarizes them for their pages. A
``LabTrial`` is one trial's station (the robot on a graph of its own, with rosapi), a
bridge server for that graph alone on a unix socket (which the sandbox relays to
``ws://127.0.0.1:9090``), and a recorder of every topic into ``OUT/trial.mcap``. A
trial whose repository brings its own interface definitions has a type registry of its
own (``labd.graph.definitions``), so its types reach no other trial and no live robot,
and the record holds their schemas. In lockstep the controller advances the task with
``/lab/step``; with ``realtime = true`` a ``LiveRunner`` steps it on the wall clock.
"""

from __future__ import annotations

import importlib.util
import json
import logging
import struct
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from mcap.exceptions import McapError
from zstandard import ZstdError

from labd import offload
from labd.bridge.server import BridgeServer
from labd.config import BridgeConfig
from labd.errors import InterfaceError, LabError
from labd.exports import write_dataset
from labd.graph.definitions import trial_types
from labd.graph.names import Namespace
from labd.graph.types import TypeRegistry
from labd.match import LabMatch
from labd.recorded import StationLab
from labd.recorder import (
    data_digest,
    digest_topics,
    first_difference,
    read_attachments,
    read_manifest,
)
from labd.recorder.summary import summary_blob
from labd.replay import replay_filed
from labd.sim import registry
from repository.benchmark import Benchmark
from repository.blobs import digest_of
from repository.errors import ExportError
from repository.evaluation import Suite
from repository.manifest import Manifest, Versions
from repository.trial import PinnedRecord, Value
from repository.well_known import OUTCOME
from scheduler.errors import InvalidRequest, TrialError
from scheduler.host import (
    MatchSetup,
    RecordFacts,
    Replayed,
    TrialSetup,
)

log = logging.getLogger("labd.trial")
MAX_CLIENTS = 16  # bridge connections a trial's controller may open
RECORD_HELPERS = 2  # helper processes for summaries and replays (one per core here)
VIDEO_NICE = 19  # background videos are rendered when nothing else wants the CPU
HELPER_START = 10.0  # seconds a helper's first call may take to import what it needs
SUMMARY_BLOB = "labd.recorder.summary:summary_blob"
REPLAY_FILED = "labd.replay:replay_filed"


class LabHost:
    """The lab's tasks, trials and records, for the scheduler (``scheduler.host``)."""

    def __init__(
        self, types: TypeRegistry | None = None, config: BridgeConfig | None = None
    ) -> None:
        self.types = types or TypeRegistry.default()
        # records are worked on in helper processes, which know the lab's own types only
        self._own_types = not self.types.standard
        self.config = config or BridgeConfig(port=0, max_connections=MAX_CLIENTS)

    def tasks(self) -> list[str]:
        return registry.names()

    def check(self, task: str, params: Mapping[str, Any]) -> dict[str, Value]:
        try:
            return registry.validate(task, params)
        except LabError as err:
            raise InvalidRequest(str(err)) from None

    def open(self, setup: TrialSetup, *, out: Path) -> LabTrial:
        types = self.types
        if setup.interfaces:
            try:
                types = trial_types(self.types, setup.interfaces)
            except InterfaceError as err:
                raise TrialError(f"the repository's interfaces: {err}") from None
        try:
            return LabTrial(self, setup, out=out, types=types)
        except LabError as err:
            raise TrialError(f"the task {setup.task} could not be built: {err}") from None

    def benchmark(self, name: str) -> Benchmark:
        try:
            return registry.benchmark(name)
        except LabError as err:
            raise InvalidRequest(str(err)) from None

    def sides(self, task: str) -> Sequence[str]:
        try:
            return registry.get(task).sides
        except LabError as err:
            raise InvalidRequest(str(err)) from None

    def open_match(self, setup: MatchSetup, *, out: Path) -> LabMatch:
        try:
            return LabMatch(self, setup, out=out)
        except LabError as err:
            raise TrialError(f"the task {setup.task} could not be built: {err}") from None

    def first_difference(self, a: Path, b: Path, topics: Sequence[str]) -> str | None:
        difference = first_difference(a, b, topics)
        return None if difference is None else str(difference)

    def data_digest(self, record: Path, topics: Sequence[str]) -> str:
        try:
            return data_digest(record, topics)
        except LabError as err:
            raise TrialError(f"{record.name} cannot be read as a record: {err}") from None

    def read_record(self, record: Path, topics: Sequence[str]) -> RecordFacts:
        """What the record holds of what a filing or a signature says of it: its manifest,
        its data digest over ``topics``, its ``outcome.json`` and its attachments' digests,
        read within the archive's limits (``TrialError`` if it is no readable record)."""
        attachments: dict[str, str] = {}
        outcome = None
        try:
            manifest = read_manifest(record)
            digest = data_digest(record, topics)
            for attachment in read_attachments(record):  # one at a time: a few MiB each
                attachments[attachment.name] = digest_of(attachment.data)
                if attachment.name == OUTCOME:
                    outcome = json.loads(attachment.data)
        except (McapError, ZstdError, struct.error, EOFError, ValueError) as err:
            raise TrialError(f"{record.name} cannot be read as a record: {err}") from None
        if manifest is not None and not isinstance(manifest, dict):
            raise TrialError(f"{record.name}: its manifest is not a JSON object")
        return RecordFacts(
            manifest, digest, outcome if isinstance(outcome, dict) else None, attachments
        )

    def task_version(self, task: str) -> str:
        try:
            return registry.get(task).version
        except LabError as err:
            raise InvalidRequest(str(err)) from None

    def suites(self, task: str) -> Sequence[Suite]:
        try:
            return registry.get(task).suites
        except LabError as err:
            raise InvalidRequest(str(err)) from None

    def digest_topics(self, task: str) -> list[str]:
        try:
            observations, commands = registry.get(task).topics()
        except LabError as err:
            raise InvalidRequest(str(err)) from None
        return digest_topics(observations, commands)

    def dataset(self, records: Sequence[tuple[PinnedRecord, Path]], out: Path) -> None:
        try:
            write_dataset([(r.model_dump(mode="json"), path) for r, path in records], out)
        except (ExportError, LabError) as err:
            raise TrialError(
                f"the data the trial learns from could not be converted: {err}"
            ) from None

    def summarize(self, mcap: Path, *, seconds: float) -> bytes:
        """The record's page summary (``labd.recorder.summary``; ``SummaryError``), made
        in a helper process (``labd.offload``) unless this host has types of its own."""
        if self._own_types:
            return summary_blob(mcap, types=self.types, seconds=seconds)
        helpers = offload.pool("records", RECORD_HELPERS)
        return helpers.call(SUMMARY_BLOB, mcap, seconds=seconds, timeout=seconds + HELPER_START)  # type: ignore[no-any-return]

    def replay(self, mcap: Path, out: Path, *, seconds: float | None = None) -> Replayed:
        """Replay a filed record (``labd.replay``): its verdict, without a video; in a
        helper process unless this host has types of its own."""
        if self._own_types:
            return replay_filed(mcap, out, self.types)
        helpers = offload.pool("records", RECORD_HELPERS)
        timeout = None if seconds is None else seconds + HELPER_START
        return helpers.call(REPLAY_FILED, mcap, out, timeout=timeout)  # type: ignore[no-any-return]

    def video(
        self, mcap: Path, out: Path, *, seconds: float | None = None, background: bool = True
    ) -> Path | None:
        """Render the filed record's first camera at 10 frames a second into ``out``
        (``labd.replay``), in a helper process (of the idle scheduling class if
        ``background``); None if the record has no camera to render, or cannot be
        replayed here."""
        if self._own_types:
            return replay_filed(mcap, out, self.types, video=True).video
        if background:
            helpers = offload.pool("background videos", 1, nice=VIDEO_NICE, idle=True)
        else:
            helpers = offload.pool("videos", 2)
        timeout = None if seconds is None else seconds + HELPER_START
        done: Replayed = helpers.call(REPLAY_FILED, mcap, out, video=True, timeout=timeout)
        return done.video


class LabTrial(StationLab):
    """One trial's robot, private bridge and recorder (``scheduler.host.TrialLab``)."""

    def __init__(
        self, host: LabHost, setup: TrialSetup, *, out: Path, types: TypeRegistry | None = None
    ) -> None:
        realtime = setup.controller.realtime
        super().__init__(
            types or host.types,  # with the repository's own types, if it has any
            host.config,
            setup.task,
            setup.values,
            setup.seed,
            out=out,
            realtime=realtime,
            blind=setup.blind,
        )
        sim = self.robot.sim
        self.manifest = Manifest.trial(
            code=setup.code,
            controller=setup.controller,
            task=self._task_version(),
            parameters=setup.values,
            seed=setup.seed,
            runtime=setup.runtime,
            versions=Versions.here(),
            model_sha256=sim.model_digest(),
            data=setup.data,
            blind=setup.blind,
        )
        # a task teams play: the lone controller plays the first side, and names its
        # topics as a team does (/player_0/action), the record keeping the graph's
        sides = sim.spec.sides
        namespaces = {"trial": Namespace("/" + sides[0])} if sides else None
        self.bridge = BridgeServer(
            {"trial": self.station.graph}, host.config, namespaces=namespaces
        )
        self.bridges = (self.bridge,)

    async def start(self, socket: Path) -> None:
        await self._start([socket])


def client_library() -> Path:
    """The folder of the ``controllers`` package, shipped into the controller runtime."""
    found = importlib.util.find_spec("controllers")
    if found is None or not found.submodule_search_locations:
        raise LabError("the lab's client library (the controllers package) is missing")
    return Path(next(iter(found.submodule_search_locations)))
