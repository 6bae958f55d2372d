"""Driving a live robot: one driver at a time, and each drive recorded as a demonstration.

A live robot of ``labd serve`` has at most one **driver**, the client whose commands it
obeys; everyone else watches (cameras, state) and is refused a command with a status
saying who drives. A client becomes the driver by calling ``/lab/drive``
(``lab_msgs/srv/Drive``: its session and interface variant are recorded), or simply by
commanding while nobody drives; it stops by calling ``/lab/release``, by leaving, or
when the episode ends. ``/lab/driver`` (``lab_msgs/msg/Driver``, latched) says who drives.

Each drive is a **session**: the robot starts a new episode (the next seed), a recorder
records the episode from its first tick, and when the session ends (the driver released,
left, or the episode ended) the record is finished and handed to ``file``: the lab's
service files it in the archive as a trial of kind ``demonstration``, under the driver,
the robot, the task, the seed and the interface. A robot nobody drove files nothing.

**Who drove** is who the lab knows the client to be: the user of the key that opened its
connection (with reservations, only a key of the slot running now drives), else a guest
name the lab makes of the connection, ``guest:client_N``. The ``user`` a client types in
``/lab/drive`` is never taken for it: the manifest keeps it apart, as
``driver.claimed_user``, a claim nobody checked. The lab's own drivers (a scripted
demonstration, through ``take``) name their user.

**What a record holds**: the robot's messages, and its driver's commands and
``/ux/events``; nothing a watcher publishes, on any topic. What a client gives
``/lab/drive`` (session, interface, user) is data, at most ``max_text`` printable
characters each; the record's folder is named by the lab.

**What is filed** (``DriveLimits``): a client's drive that gave no command, or that ran
fewer than ``min_ticks`` ticks, files nothing; nor one whose user, or else address, has
filed ``filings_per_minute`` drives in the last minute, over all the lab's robots. When a
record reaches ``max_record`` bytes, the driver's events are no longer recorded and the
drive ends at the next tick, filed as it stands. The driver's reply to ``/lab/release``
(or to ``/lab/drive`` again) says what became of its drive.

**One drive's errors are its own.** Anything that fails while one drive is recorded or
filed (a folder that cannot be made, a full disk, a bug) drops that drive's record, is
logged with its traceback and told to the driver (in its reply when there is one, and
on ``/rosout``); the robot steps on for everyone.
"""

from __future__ import annotations

import logging
import math
import secrets
import shutil
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from labd.config import DriveLimits
from labd.errors import GraphError
from labd.graph.graph import Node, Side, Topic
from labd.graph.message import Message
from labd.graph.services import ServiceCall
from labd.recorder import Recorder, digest_topics
from labd.recorder.record import Keep
from labd.station import Station
from repository.digests import readable_json
from repository.manifest import Driver, Manifest, TaskVersion, Versions
from repository.trial import EpisodeStatus, Kind, Order
from repository.units import MiB
from repository.well_known import MANIFEST, OUTCOME, UX_EVENTS

log = logging.getLogger("labd.live")
DRIVER = "/lab/driver"
WARN = 30  # rcl_interfaces/msg/Log's level for a warning
MINUTE = 60.0  # seconds over which filings are counted
TEXTS = ("session", "interface", "user")  # what a client's /lab/drive says


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


class BadDriveText(GraphError):
    """A text of a ``/lab/drive`` request that is too long or holds control characters."""

    def __init__(self, name: str, limit: int, value: str) -> None:
        self.name = name
        self.limit = limit
        super().__init__(
            f"/lab/drive: the {name} may be at most {limit} characters, none of them a"
            f" control character; this one has {len(value)}"
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
    manifest: Manifest
    manifest_digest: str
    data_digest: str
    digest_topics: list[str]
    metrics: dict[str, Any]
    achieved: bool
    reason: str

    @property
    def order(self) -> Order:
        """What the archive files the drive as: a public demonstration of the robot's task
        and seed, with no code (no ref, no commit)."""
        return Order(
            repository=f"robot:{self.robot}",
            task=self.task,
            params=self.params,
            seed=self.seed,
            public=True,
            kind=Kind.DEMONSTRATION,
        )


class Filings:
    """The drives filed in the last minute, per user or address. A lab's robots share
    one, so that a client cannot fill the archive by driving each robot in turn."""

    def __init__(self, per_minute: int) -> None:
        self.per_minute = per_minute  # 0: no limit
        self._times: dict[str, deque[float]] = {}

    def wait(self, who: str, now: float) -> float:
        """Seconds before ``who`` may file again (0: now)."""
        times = self._times.get(who)
        if not self.per_minute or times is None:
            return 0.0
        while times and times[0] <= now - MINUTE:
            times.popleft()
        if len(times) < self.per_minute:
            return 0.0
        return times[-self.per_minute] + MINUTE - now

    def add(self, who: str, now: float) -> None:
        """``who`` filed a drive now (and everyone's filings of long ago are forgotten)."""
        for key in [k for k, t in self._times.items() if t[-1] <= now - MINUTE]:
            del self._times[key]
        self._times.setdefault(who, deque()).append(now)


@dataclass
class _Session:
    node: Node
    user: str  # who the lab knows drives
    interface: str
    session: str
    claimed_user: str = ""  # the user the client typed, unchecked
    client: bool = True  # taken by a client of the bridge: the filing rules apply
    recorder: Recorder | None = None
    manifest: Manifest | None = None  # the drive being recorded's
    folder: Path | None = None
    commands: int = 0  # the driver's commands in the episode being recorded
    full: bool = False  # the record reached its size limit
    trouble: str = ""  # why the episode being driven is not recorded
    fate: str = ""  # what became of the drive's last record: filed, or why not


class Driving:
    """The driver of the robot in ``station``, and the recording of each drive.

    ``filings`` counts filings per user or address; the lab shares one among its robots.
    """

    def __init__(
        self,
        station: Station,
        *,
        work: Path | None,
        file: Callable[[Demonstration], None] | None = None,
        reserved: bool = False,
        limits: DriveLimits | None = None,
        filings: Filings | None = None,
    ) -> None:
        self.station = station
        self.reserved = reserved
        self.robot = station.robot
        self.name = station.name
        self.work = work  # where sessions are recorded; None: drives are not recorded
        self.file = file
        self.limits = limits or DriveLimits()
        self.filings = filings or Filings(self.limits.filings_per_minute)
        self.current: _Session | None = None
        self.filed: list[Demonstration] = []
        self._commands = frozenset(c.name for c in self.robot.sim.task.commands)
        node = self.robot.node
        self._driver = node.advertise(DRIVER, "lab_msgs/msg/Driver", latch=True, own=True)
        node.provide_service("/lab/drive", "lab_msgs/srv/Drive", self._drive_service)
        node.provide_service("/lab/release", "std_srvs/srv/Trigger", self._release_service)
        self.robot.command_gate = self.admit
        self.robot.on_tick = self._tick
        self.robot.before_reset = self._episode_replaced
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
            self._take_for_client(sender)
        elif sender is not self.current.node:
            raise NotDriving(self.name, self.current.user)
        if self.current is not None and topic in self._commands:
            self.current.commands += 1

    def take(self, node: Node, *, user: str, interface: str = "", session: str = "") -> None:
        """Make ``node`` the driver, for the lab's own code (a scripted driver): a new
        episode, and a recorded session, under ``user`` as given (a key's user with
        reservations); the filing rules of clients' drives do not apply."""
        if self.reserved and node.user is not None:
            user = node.user
        self._begin(_Session(node, user, interface, session or secrets.token_hex(6), client=False))

    def _take_for_client(
        self, node: Node, *, interface: str = "", session: str = "", claimed: str = ""
    ) -> None:
        """Make a bridge client the driver, under the name the lab knows it by."""
        user = node.user or "guest:" + node.name.rsplit("/", 1)[-1]
        self._begin(
            _Session(
                node,
                user,
                interface or node.interface,
                session or secrets.token_hex(6),
                claimed_user=claimed,
            )
        )

    def _begin(self, session: _Session) -> None:
        self.current = session
        self.robot.reset()  # a new episode for the drive, recorded from its first tick
        self._announce()
        log.info("%s: %s drives (seed %d)", self.name, session.user, self.robot.sim.seed)

    def release(self, reason: str) -> Demonstration | None:
        """End the drive: the session's record is finished and filed (or dropped, its
        ``fate`` saying why)."""
        session, self.current = self.current, None
        self._announce()
        if session is None:
            return None
        return self._finish(session, reason)

    def _gone(self, node: Node) -> None:
        if self.current is not None and node is self.current.node:
            self.release(f"the driver left at tick {self.robot.sim.tick}")

    def _tick(self) -> None:
        """After every tick: an episode that ended ends its recording (the driver stays
        for the next one); a record past its size limit ends the drive."""
        session = self.current
        if session is None:
            return
        if not self.robot.sim.running:
            self._finish(session, "")
        elif session.recorder is not None and self._full(session):
            limit = self.limits.max_record / MiB
            self.release(
                f"the record reached its size limit of {limit:g} MiB at tick {self.robot.sim.tick}"
            )

    def _full(self, session: _Session) -> bool:
        limit = self.limits.max_record
        recorder = session.recorder
        return session.full or bool(limit and recorder and recorder.size >= limit)

    def _episode_replaced(self) -> None:
        """A reset under way, its episode still readable: a recording of it is finished."""
        session = self.current
        if session is not None and session.recorder is not None:
            self._finish(session, f"the episode was reset at tick {self.robot.sim.tick}")

    def _new_episode(self) -> None:
        """A new episode (a reset, or the next after one ended): record it if driven."""
        if self.current is not None:
            self._start_recording(self.current)

    # -- services -----------------------------------------------------------------------

    def _drive_service(self, call: ServiceCall) -> None:
        request = call.request.data
        caller = call.caller
        if caller is None or (self.reserved and caller.user is None):
            call.reply({"success": False, "message": str(NotReserved(self.name)), "seed": 0})
            return
        if self.current is not None and self.current.node is not caller:
            call.reply({"success": False, "message": f"{self.current.user} drives", "seed": 0})
            return
        try:
            texts = {name: _text(request, name, self.limits.max_text) for name in TEXTS}
        except BadDriveText as err:
            call.reply({"success": False, "message": str(err), "seed": 0})
            return
        previous = self.current
        if previous is not None:  # the driver asks again: a fresh episode
            self.release("the driver started anew")
        self._take_for_client(
            caller, interface=texts["interface"], session=texts["session"], claimed=texts["user"]
        )
        seed = self.robot.sim.seed
        message = f"you drive; episode seed {seed}"
        if self.current is not None and self.current.trouble:
            message += f"; {self.current.trouble}"
        if previous is not None and previous.fate:
            message += f"; your last drive is {previous.fate}"
        call.reply({"success": True, "message": message, "seed": seed})

    def _release_service(self, call: ServiceCall) -> None:
        session = self.current
        if session is None or session.node is not call.caller:
            call.reply({"success": False, "message": "you do not drive this robot"})
            return
        self.release("the driver released the robot")
        said = f"released; the drive is {session.fate}" if session.fate else "released"
        call.reply({"success": True, "message": said})

    # -- recording ----------------------------------------------------------------------

    def _start_recording(self, session: _Session) -> None:
        """Record the new episode from its first tick (when drives are recorded): the
        robot publishes that tick right after."""
        session.commands, session.full, session.trouble = 0, False, ""
        if self.work is None:
            return
        sim = self.robot.sim
        manifest = Manifest.drive(
            robot=self.name,
            task=TaskVersion(sim.spec.name, sim.spec.version),
            parameters=sim.values,
            seed=sim.seed,
            driver=Driver(session.user, session.interface, session.session, session.claimed_user),
            versions=Versions.here(),
            model_sha256=sim.model_digest(),
        )
        # Named by the lab: nothing a client says is ever part of a path.
        folder = self.work / f"{self.name}-{sim.seed}-{secrets.token_hex(6)}"
        topics = digest_topics((o.name for o in sim.task.observations), self._commands)
        try:
            recorder = Recorder(
                self.station.graph,
                folder,
                digest_topics=topics,
                manifest=manifest.to_json(),
                keep=self._keeper(session),
            )
        except Exception as err:  # the drive goes on, unrecorded; the robot steps on
            text = f"this drive is not recorded: its record could not be made ({err})"
            log.exception("%s: the drive of %s: %s", self.name, session.user, text)
            shutil.rmtree(folder, ignore_errors=True)
            self._trouble(session, text)
            return
        session.manifest = manifest
        session.folder = folder
        session.recorder = recorder

    def _keeper(self, session: _Session) -> Keep:
        """What the session's record keeps: the robot's messages, and its driver's
        commands and /ux/events (the events only while the record is within its limit)."""
        robot, driver, commands = self.robot.node, session.node, self._commands
        limit = self.limits.max_record

        def keep(topic: Topic, message: Message, side: Side, sender: Node | None) -> bool:
            if sender is robot:
                return True
            if sender is not driver or (topic.name not in commands and topic.name != UX_EVENTS):
                return False
            recorder = session.recorder
            if topic.name != UX_EVENTS or not limit or recorder is None:
                return True
            if recorder.size + len(message.cdr()) > limit:
                session.full = True  # the drive ends at the next tick
                return False
            return True

        return keep

    def _finish(self, session: _Session, reason: str) -> Demonstration | None:
        """Finish the session's record and file it, or drop it saying why (``fate``)."""
        recorder, folder = session.recorder, session.folder
        if recorder is None or folder is None:
            return None
        session.recorder = None
        session.folder = None
        try:
            refused = self._refusal(session) if session.client else ""
            if refused:
                recorder.discard()
                shutil.rmtree(folder, ignore_errors=True)
                session.fate = f"not filed: {refused}"
                log.info("%s: the drive of %s is %s", self.name, session.user, session.fate)
                return None
            demo = self._demonstration(session, recorder, folder, reason)
            if session.client:
                self.filings.add(_filer(session.node)[0], self.robot.wall_clock())
            session.fate = "filed as a demonstration"
            log.info("%s: the drive of %s ended: %s", self.name, session.user, demo.reason)
            self.filed.append(demo)
            if self.file is not None:
                self.file(demo)
            return demo
        except Exception as err:  # this drive's record is lost; the robot steps on
            text = f"this drive is not filed: {err}"
            log.exception("%s: the drive of %s: %s", self.name, session.user, text)
            recorder.discard()
            shutil.rmtree(folder, ignore_errors=True)
            self._trouble(session, text)
            return None

    def _refusal(self, session: _Session) -> str:
        """Why a client's drive is no demonstration to file ("" when it is one)."""
        ticks, least = self.robot.sim.tick, self.limits.min_ticks
        if session.commands == 0:
            return "no command was given"
        if ticks < least:
            return f"shorter than {least} ticks ({ticks})"
        who, whence = _filer(session.node)
        wait = self.filings.wait(who, self.robot.wall_clock())
        if wait > 0:
            return (
                f"{self.filings.per_minute} drives were filed {whence} in the last minute, the"
                f" most the lab files; the next may be filed in {math.ceil(wait)} s"
            )
        return ""

    def _demonstration(
        self, session: _Session, recorder: Recorder, folder: Path, reason: str
    ) -> Demonstration:
        sim = self.robot.sim
        achieved = sim.status is EpisodeStatus.SUCCEEDED
        said = reason or (
            f"the task was achieved at tick {sim.tick}: {sim.reason}"
            if achieved
            else f"the episode ended at tick {sim.tick} without success: {sim.status}: {sim.reason}"
        )
        metrics = dict(sim.metrics())
        outcome = {"achieved": achieved, "reason": said, "metrics": metrics}
        manifest = session.manifest
        assert manifest is not None  # recorded since the drive began
        summary = recorder.finish(
            attachments={
                MANIFEST: ("application/json", readable_json(manifest.to_json())),
                OUTCOME: ("application/json", readable_json(outcome)),
                **sim.model_files(),
            }
        )
        return Demonstration(
            robot=self.name,
            task=sim.spec.name,
            seed=sim.seed,
            params=dict(sim.values),
            user=session.user,
            interface=session.interface,
            session=session.session,
            folder=folder,
            manifest=manifest,
            manifest_digest=manifest.digest,
            data_digest=summary.data_digest,
            digest_topics=sorted(recorder.digest_topics),
            metrics={k: v for k, v in metrics.items() if not _nan(v)},
            achieved=achieved,
            reason=said,
        )

    def _trouble(self, session: _Session, text: str) -> None:
        """One drive's error (logged where it was caught, with its traceback): told to
        the driver, whose drive has no record now."""
        session.trouble = text
        session.fate = text.removeprefix("this drive is ")
        self.station.graph.rosout(
            WARN, "labd.live", f"{self.name}: the drive of {session.user}: {text}"
        )
        self._announce()

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


def _text(request: dict[str, Any], name: str, limit: int) -> str:
    """A text of a ``/lab/drive`` request, checked: data, never a name of anything."""
    value = str(request.get(name) or "")
    if len(value) > limit or not value.isprintable():
        raise BadDriveText(name, limit, value)
    return value


def _filer(node: Node) -> tuple[str, str]:
    """Whom a client's filings count against, and how to tell them: its key's user, else
    its address (a connection of the lab's own: its node)."""
    if node.user is not None:
        return f"user {node.user}", f"by {node.user}"
    if node.address is not None:
        return f"address {node.address}", "from your address"
    return f"node {node.name}", f"by {node.name}"


def _nan(value: Any) -> bool:
    return isinstance(value, float) and not math.isfinite(value)
