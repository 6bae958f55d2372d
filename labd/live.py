"""Driving a live robot: one driver at a time, and each drive recorded as a demonstration.

A live robot of ``labd serve`` has at most one **driver**, the client whose commands it
obeys; everyone else watches (cameras, state) and is refused a command with a status
saying who drives. A client becomes the driver by calling ``/lab/drive``
(``lab_msgs/srv/Drive``: its session and interface variant are recorded), or simply by
commanding while nobody drives; it stops by calling ``/lab/release``, by leaving, or
when the episode ends. ``/lab/driver`` (``lab_msgs/msg/Driver``, latched) says who drives.

Each drive is a **session**: the robot starts a new episode (the next seed), a recorder
records every topic of the robot's graph from that episode's first tick, and when the
session ends (the driver released, left, or the episode ended) the record is finished
and handed to ``file``: the lab's service files it in the archive as a trial of kind
``demonstration``, under the driver, the robot, the task, the seed and the interface.
A robot nobody drove files nothing.

With reservations on (``reserved``), only a client whose key opened the robot (a key of
the slot running now: the bridge put its user on the client's node) may drive; anyone
else watches, and is told how to book. The drive is filed under the key's user, never
under a name the client gives.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import secrets
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from labd.errors import GraphError
from labd.graph.graph import Node, Side
from labd.graph.services import ServiceCall
from labd.recorder import Recorder, canonical_json
from labd.sim.base import SUCCEEDED
from labd.station import Station
from scheduler.manifest import SCHEMA, versions

log = logging.getLogger("labd.live")
DRIVER = "/lab/driver"


class NotDriving(GraphError):
    """A command from a client that does not drive the robot."""

    def __init__(self, robot: str, driver: str) -> None:
        self.robot = robot
        self.driver = driver
        super().__init__(
            f"{robot} is driven by {driver}; you are watching. You may drive when they leave"
            " (or release it)"
        )


class NotReserved(GraphError):
    """A command from a client without a key of the slot running now."""

    def __init__(self, robot: str) -> None:
        self.robot = robot
        super().__init__(
            f"{robot} is driven only in a reserved slot; you are watching. To drive, book a"
            " slot (the lab's /reservations page, or labd reserve) and connect with its key"
        )


@dataclass
class Demonstration:
    """A finished drive: its record's folder and what the archive files of it."""

    robot: str
    task: str
    seed: int
    params: dict[str, Any]
    user: str
    interface: str
    session: str
    folder: Path
    manifest: dict[str, Any]
    manifest_digest: str
    data_digest: str
    digest_topics: list[str]
    metrics: dict[str, Any]
    achieved: bool
    reason: str


@dataclass
class _Session:
    node: Node
    user: str
    interface: str
    session: str
    recorder: Recorder | None = None
    manifest: dict[str, Any] = field(default_factory=dict)
    folder: Path | None = None


class Driving:
    """The driver of the robot in ``station``, and the recording of each drive."""

    def __init__(
        self,
        station: Station,
        *,
        work: Path | None,
        file: Callable[[Demonstration], None] | None = None,
        reserved: bool = False,
    ) -> None:
        self.station = station
        self.reserved = reserved
        self.robot = station.robot
        self.name = station.name
        self.work = work  # where sessions are recorded; None: drives are not recorded
        self.file = file
        self.current: _Session | None = None
        self.filed: list[Demonstration] = []
        node = self.robot.node
        self._driver = node.advertise(DRIVER, "lab_msgs/msg/Driver", latch=True, own=True)
        node.provide_service("/lab/drive", "lab_msgs/srv/Drive", self._drive_service)
        node.provide_service("/lab/release", "std_srvs/srv/Trigger", self._release_service)
        self.robot.command_gate = self.admit
        self.robot.on_tick = self._tick
        self.robot.on_reset = self._new_episode
        station.graph.node_gone.append(self._gone)
        self._announce()

    # -- who drives ---------------------------------------------------------------------

    def admit(self, sender: Node | None, topic: str) -> None:
        """The robot's gate: a command from the driver, or from anyone while nobody drives
        (who then drives); anyone else is refused (``NotDriving``). With reservations,
        a client without a key of the slot is refused first (``NotReserved``)."""
        if sender is None or sender.side is Side.LAB:
            return
        if self.reserved and sender.user is None:
            raise NotReserved(self.name)
        if self.current is None:
            self.take(sender)
        elif sender is not self.current.node:
            raise NotDriving(self.name, self.current.user)

    def take(self, node: Node, *, user: str = "", interface: str = "", session: str = "") -> None:
        """Make ``node`` the driver: a new episode, and a recorded session. With
        reservations the drive is the key's user's, whatever name was given."""
        if self.reserved and node.user is not None:
            user = node.user
        self.current = _Session(
            node,
            user or node.user or node.name,
            interface,
            session or secrets.token_hex(6),
        )
        self.robot.reset()  # a new episode for the drive, recorded from its first tick
        self._announce()
        log.info("%s: %s drives (seed %d)", self.name, self.current.user, self.robot.sim.seed)

    def release(self, reason: str) -> Demonstration | None:
        """End the drive: the session's record is finished and filed."""
        session, self.current = self.current, None
        self._announce()
        if session is None:
            return None
        return self._finish(session, reason)

    def _gone(self, node: Node) -> None:
        if self.current is not None and node is self.current.node:
            self.release(f"the driver left at tick {self.robot.sim.tick}")

    def _tick(self) -> None:
        """An episode that ends ends its recording; the driver stays for the next one."""
        if self.current is not None and not self.robot.sim.running:
            self._finish(self.current, "")

    def _new_episode(self) -> None:
        """A new episode (a reset, or the next after one ended): record it if driven."""
        if self.current is None:
            return
        if self.current.recorder is not None:
            self._finish(self.current, f"the episode was reset at tick {self.robot.sim.tick}")
        self._start_recording()

    # -- services -----------------------------------------------------------------------

    def _drive_service(self, call: ServiceCall) -> None:
        request = call.request.data
        caller = call.caller
        if self.reserved and (caller is None or caller.user is None):
            call.reply({"success": False, "message": str(NotReserved(self.name)), "seed": 0})
            return
        if self.current is not None and self.current.node is not caller:
            call.reply({"success": False, "message": f"{self.current.user} drives", "seed": 0})
            return
        if self.current is not None:  # the driver asks again: a fresh episode
            self.release("the driver started anew")
        self.take(
            caller,
            user=str(request.get("user") or ""),
            interface=str(request.get("interface") or ""),
            session=str(request.get("session") or ""),
        )
        seed = self.robot.sim.seed
        call.reply({"success": True, "message": f"you drive; episode seed {seed}", "seed": seed})

    def _release_service(self, call: ServiceCall) -> None:
        if self.current is None or self.current.node is not call.caller:
            call.reply({"success": False, "message": "you do not drive this robot"})
            return
        self.release("the driver released the robot")
        call.reply({"success": True, "message": "released"})

    # -- recording ----------------------------------------------------------------------

    def _start_recording(self) -> None:
        """Record the new episode from its first tick (when drives are recorded): the
        robot publishes that tick right after."""
        session = self.current
        assert session is not None
        if self.work is None:
            return
        sim = self.robot.sim
        manifest = {
            "schema": SCHEMA,
            "kind": "demonstration",
            "robot": self.name,
            "task": {"name": sim.spec.name, "version": sim.spec.version},
            "parameters": dict(sorted(sim.values.items())),
            "seed": sim.seed,
            "live": True,
            "controller": {"realtime": True},
            "driver": {
                "user": session.user,
                "interface": session.interface,
                "session": session.session,
            },
            "versions": versions(),
            "model_sha256": sim.model_digest(),
        }
        folder = self.work / f"{self.name}-{session.session}-{sim.seed}"
        topics = {o.name for o in sim.task.observations} | {c.name for c in sim.task.commands}
        session.manifest = manifest
        session.folder = folder
        session.recorder = Recorder(
            self.station.graph,
            folder,
            digest_topics=sorted(topics | {"/clock", "/lab/episode"}),
            manifest=manifest,
        )

    def _finish(self, session: _Session, reason: str) -> Demonstration | None:
        recorder, folder = session.recorder, session.folder
        if recorder is None or folder is None:
            return None
        sim = self.robot.sim
        achieved = sim.status == SUCCEEDED
        said = reason or (
            f"the task was achieved at tick {sim.tick}: {sim.reason}"
            if achieved
            else f"the episode ended at tick {sim.tick} without success: {sim.status}: {sim.reason}"
        )
        metrics = dict(sim.metrics())
        outcome = {"achieved": achieved, "reason": said, "metrics": metrics}
        summary = recorder.finish(
            attachments={
                "manifest.json": ("application/json", _json(session.manifest)),
                "outcome.json": ("application/json", _json(outcome)),
                **sim.model_files(),
            }
        )
        session.recorder = None
        session.folder = None
        demo = Demonstration(
            robot=self.name,
            task=sim.spec.name,
            seed=sim.seed,
            params=dict(sim.values),
            user=session.user,
            interface=session.interface,
            session=session.session,
            folder=folder,
            manifest=session.manifest,
            manifest_digest=hashlib.sha256(canonical_json(session.manifest).encode()).hexdigest(),
            data_digest=summary.data_digest,
            digest_topics=sorted(recorder.digest_topics),
            metrics={k: v for k, v in metrics.items() if not _nan(v)},
            achieved=achieved,
            reason=said,
        )
        log.info("%s: the drive of %s ended: %s", self.name, session.user, said)
        self.filed.append(demo)
        if self.file is not None:
            self.file(demo)
        return demo

    def _announce(self) -> None:
        session = self.current
        sim = self.robot.sim
        self._driver.publish(
            {
                "stamp": {
                    "sec": sim.time_ns // 1_000_000_000,
                    "nanosec": sim.time_ns % 1_000_000_000,
                },
                "driver": session.user if session else "",
                "session": session.session if session else "",
                "interface": session.interface if session else "",
                "seed": sim.seed,
                "recording": bool(session and session.recorder),
            }
        )

    def close(self) -> None:
        """Finish a drive still under way (the lab stops): its record is filed."""
        if self.current is not None:
            self.release("the lab stopped")


def _nan(value: Any) -> bool:
    return isinstance(value, float) and not math.isfinite(value)


def _json(value: Any) -> bytes:
    return (json.dumps(value, indent=2, sort_keys=True, default=str) + "\n").encode()
