"""A station recorded for the runner: what a trial and a match's leg share.

The robot runs its task on a graph of its own with rosapi (``labd.station``); the
runner watches its ticks (when the first and the newest came, whether the episode is
over) and judges by them; a recorder holds every topic in ``OUT/trial.mcap``, the
manifest first. The bridges the controllers reach it through are the subclass's:
one for a trial (``labd.trial.LabTrial``), one per side for a match's leg
(``labd.match.LabMatch``).
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from labd.bridge.server import BridgeServer
from labd.config import BridgeConfig
from labd.errors import RecordError
from labd.graph.types import TypeRegistry
from labd.recorder import Recorder, digest_topics
from labd.sim.robot import LiveRunner
from labd.station import Station
from repository.manifest import Manifest, TaskVersion
from repository.trial import EpisodeStatus, Value
from scheduler.errors import TrialError
from scheduler.host import Attachments, Episode


class StationLab:
    """What a trial and a match's leg share: the robot on a graph of its own (with
    rosapi), its ticks as the runner watches them, and the recorder of every topic.
    The bridges the controllers reach it through are the subclass's (``bridges``)."""

    manifest: Manifest
    bridges: Sequence[BridgeServer]

    def __init__(
        self,
        types: TypeRegistry,
        config: BridgeConfig,
        task: str,
        values: Mapping[str, Value],
        seed: int,
        *,
        out: Path,
        realtime: bool = False,
        blind: bool = False,
    ) -> None:
        self.task = task
        self.realtime = realtime
        self.out = out
        limit = float(values["time_limit"]) if realtime and "time_limit" in values else None
        self.station = Station(
            types,
            "trial",
            task,
            dict(values),
            seed,
            live=realtime,
            protected_prefixes=config.protected_prefixes,
            time_limit=limit,
            blind=blind,
        )
        self.robot = self.station.robot
        self.robot.on_tick = self._tick
        self.recorder: Recorder | None = None
        self.first_tick_at: float | None = None  # the loop's times of the first step,
        self.last_tick_at: float | None = None  # and of the newest
        self._ended: asyncio.Future[None] | None = None  # what ``ended`` waits for
        self._live: asyncio.Task[None] | None = None
        self._finished: str | None = None
        task_obj = self.robot.sim.task
        self._digest_topics = digest_topics(
            [o.name for o in task_obj.observations], [c.name for c in task_obj.commands]
        )

    def _task_version(self) -> TaskVersion:
        return TaskVersion(self.task, self.robot.sim.spec.version)

    # -- what the runner reads ----------------------------------------------------------

    @property
    def digest_topics(self) -> Sequence[str]:
        return self._digest_topics

    def episode(self) -> Episode:
        sim = self.robot.sim
        return Episode(
            tick=sim.tick,
            running=sim.running,
            status=sim.status,
            reason=sim.reason,
            achieved=sim.status is EpisodeStatus.SUCCEEDED,
            diverged=sim.diverged,
        )

    def metrics(self) -> dict[str, Any]:
        return dict(self.robot.sim.metrics())

    def model_files(self) -> dict[str, tuple[str, bytes]]:
        return self.robot.sim.model_files()

    async def ended(self) -> None:
        if not self.robot.sim.running:
            return
        if self._ended is None or self._ended.done():
            self._ended = asyncio.get_running_loop().create_future()
        await self._ended

    def _tick(self) -> None:
        """After every step: when, and whether the episode is over. (The runner wakes
        at the end of the episode, or when no step came for a while, not every tick.)"""
        now = asyncio.get_running_loop().time()
        self.last_tick_at = now
        if self.first_tick_at is None:
            self.first_tick_at = now
        ended = self._ended
        if ended is not None and not ended.done() and not self.robot.sim.running:
            ended.set_result(None)

    # -- its life -----------------------------------------------------------------------

    async def _start(self, sockets: Sequence[Path]) -> None:
        """Record (the manifest first), listen on each bridge's socket, publish tick 0."""
        try:
            self.recorder = Recorder(
                self.station.graph,
                self.out,
                digest_topics=self._digest_topics,
                manifest=self.manifest.to_json(),
                defer=True,  # written once a tick's answer has left
            )
        except RecordError as err:  # the disk is full
            raise TrialError(str(err)) from None
        for bridge, socket in zip(self.bridges, sockets, strict=True):
            await bridge.start(unix_path=socket)
        self.robot.publish()  # tick 0, now that the recorder listens
        if self.realtime:
            self._live = asyncio.create_task(LiveRunner(self.robot).run(), name="trial live")

    async def finish(self, attachments: Attachments) -> str:
        if self._finished is not None:
            return self._finished
        if self._live is not None:
            self._live.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._live
        for bridge in self.bridges:
            await bridge.close()
        digest = ""
        try:
            if self.recorder is not None:
                digest = self.recorder.finish(attachments=dict(attachments)).data_digest
        except RecordError as err:  # the disk filled up: the record is gone
            raise TrialError(str(err)) from None
        finally:
            self.station.close()
            self._finished = digest
        return digest
