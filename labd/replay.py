"""Replay: re-simulate a record from its actions alone and compare what the robot did.

A trial's record holds everything that decided it: the manifest (task, version,
parameters, seed, the compiled model's digest, the simulator's versions) and every
command the controller sent, in order, between the ticks. In lockstep the simulation
is deterministic, so building the task again from the manifest and applying the
recorded commands tick by tick must give the recorded observations, byte for byte. No
controller, no sandbox, no network: a downloaded file is enough.

The record is read as ticks: everything up to and including a tick's ``/lab/episode``
is that tick. For each tick after the first, its commands (what clients published) are
applied, the task steps once, and what the robot publishes is compared with what the
record holds for that tick: "replay verified", or the first difference (tick, topic,
the field and both values). On-demand topics (cameras) are compared by topic and time,
since they were recorded only while someone watched, and the replay renders them only
for the ticks the record has them.
"""

from __future__ import annotations

import json
import logging
import math
import struct
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mcap.exceptions import McapError
from zstandard import ZstdError

from labd.errors import LabError
from labd.graph.graph import Node, Side, Topic
from labd.graph.message import Message
from labd.graph.types import TypeRegistry
from labd.recorder import read_manifest
from labd.recorder.digest import Entry, field_difference
from labd.recorder.reader import RecordedMessage, read_messages
from labd.sim import registry
from labd.station import Station
from labd.video import FIRST, Video, VideoSpec
from repository.errors import ManifestError
from repository.manifest import Manifest, Versions
from repository.well_known import EPISODE, ROSOUT, UX_EVENTS, VIDEO
from scheduler.host import Replayed

log = logging.getLogger("labd.replay")
IGNORED = frozenset({ROSOUT, UX_EVENTS, "/parameter_events"})


class ReplayError(LabError):
    """A record that cannot be replayed: the message says why and what would fix it."""


@dataclass(frozen=True)
class Divergence:
    """Where a replay first differs from its record."""

    tick: int
    topic: str
    log_time: int
    what: str

    def __str__(self) -> str:
        return f"replay diverged at tick {self.tick} on {self.topic}: {self.what}"


@dataclass
class Verdict:
    """What a replay found: verified, or the first divergence; and what it compared."""

    ticks: int = 0
    compared: int = 0  # messages compared
    divergence: Divergence | None = None
    frames: dict[str, int] = field(default_factory=dict)  # rendered frames, by output

    @property
    def verified(self) -> bool:
        return self.divergence is None

    def __str__(self) -> str:
        if self.divergence is not None:
            return str(self.divergence)
        return f"replay verified: {self.ticks} ticks, {self.compared} messages identical"

    def to_json(self) -> dict[str, Any]:
        """The verdict as JSON: what a record's ``replay.json`` holds and ``labd replay
        --json`` prints (each adds its own: the words, the video; the videos)."""
        divergence = self.divergence
        return {
            "verified": self.verified,
            "ticks": self.ticks,
            "compared": self.compared,
            "divergence": None
            if divergence is None
            else {"tick": divergence.tick, "topic": divergence.topic, "what": divergence.what},
        }


@dataclass
class _Tick:
    commands: list[RecordedMessage] = field(default_factory=list)
    observed: list[RecordedMessage] = field(default_factory=list)


def ticks_of(
    path: Path, commands: frozenset[str] = frozenset(), robot: frozenset[str] | None = None
) -> Iterator[_Tick]:
    """A record as ticks: the commands sent before each step, and what the lab then
    published (ending with ``/lab/episode``). A message on one of the ``commands`` topics
    is a command whoever sent it (a live robot's watchdog sends a stop itself); of the
    lab's other messages, those on the ``robot``'s topics (its observations, ``/clock``,
    ``/lab/episode``), since the lab's other nodes (who drives, logs) are no robot's."""
    current = _Tick()
    for message in read_messages(path):
        if message.topic in IGNORED:
            continue
        if message.side is Side.LAB and message.topic not in commands:
            if robot is not None and message.topic not in robot:
                continue
            current.observed.append(message)
            if message.topic == EPISODE:
                yield current
                current = _Tick()
        else:
            current.commands.append(message)
    if current.commands or current.observed:
        yield current


def check_manifest(manifest: Manifest, station: Station) -> None:
    """Refuse what cannot be the same simulation: another model, another simulator."""
    recorded = manifest.versions
    here = Versions.here()
    for name in ("mujoco", "dm_control"):
        then, now = getattr(recorded, name), getattr(here, name)
        if then != now:
            raise ReplayError(
                f"the record was made with {name} {then}, this lab has {name} {now}: a replay"
                f" needs the same simulator (install {name}=={then})"
            )
    digest = station.robot.sim.model_digest()
    if manifest.model_sha256 != digest:
        raise ReplayError(
            f"the task's model is not the one recorded (sha256 {digest[:12]}..., the record"
            f" has {manifest.model_sha256[:12]}...): task {manifest.task.name} has changed"
            f" since; use the labd that made it ({recorded.labd})"
        )


def replay(
    path: Path,
    types: TypeRegistry | None = None,
    *,
    renderers: Sequence[Any] = (),
) -> Verdict:
    """Replay the record at ``path`` (an MCAP file or a trial folder).

    ``renderers`` are called with the physics after every tick (videos rendered after
    the fact); they never change the verdict.
    """
    manifest = _manifest(path)
    if manifest is None:
        raise ReplayError(f"{path} holds no manifest: it is not a trial's record")
    task = manifest.task.name
    spec = registry.get(task)
    if spec.version != manifest.task.version:
        raise ReplayError(
            f"the record is of {task} version {manifest.task.version}; this lab"
            f" has version {spec.version}"
        )
    station = Station(
        types or TypeRegistry.shared(),
        "replay",
        task,
        dict(manifest.parameters),
        manifest.seed,
        live=False,
        protected_prefixes=("/protected",),
        # a live robot's episode has no time limit: it ends at its goal, or by a reset
        time_limit=math.inf if manifest.live else None,
        blind=manifest.blind,  # a held-out episode's /lab/episode, as it ran
    )
    try:
        check_manifest(manifest, station)
        _framebuffer(station, renderers)
        return _run(path, station, renderers, manifest.realtime)
    finally:
        station.close()


def _manifest(path: Path) -> Manifest | None:
    """The manifest the record holds (None: none), ``ReplayError`` if it cannot be read."""
    try:
        found = read_manifest(path)
        return None if found is None else Manifest.from_json(found)
    except (McapError, ZstdError, struct.error, EOFError, ValueError) as err:
        raise ReplayError(f"{path} cannot be read as a record: {err}") from None
    except ManifestError as err:
        raise ReplayError(f"{path}: its manifest cannot be read: {err}") from None


def _framebuffer(station: Station, renderers: Sequence[Any]) -> None:
    """Make the offscreen framebuffer large enough for the videos asked for.

    A model's framebuffer is as large as its cameras; a video may be larger. This is a
    setting of the renderer, not of the physics, and is made after the model's digest
    was checked and before anything is rendered.
    """
    sizes = [(r.spec.width, r.spec.height) for r in renderers if hasattr(r, "spec")]
    if not sizes:
        return
    visual = station.robot.sim.physics.model.vis.global_
    visual.offwidth = max(int(visual.offwidth), *(w for w, _ in sizes))
    visual.offheight = max(int(visual.offheight), *(h for _, h in sizes))


def _run(path: Path, station: Station, renderers: Sequence[Any], realtime: bool) -> Verdict:
    graph = station.graph
    robot = station.robot
    on_demand = {o.name for o in robot.sim.task.observations if o.on_demand}
    # only the task's commands move the robot; a controller's own topics are its business
    commands = {c.name for c in robot.sim.task.commands}
    produced: list[Entry] = []

    def tap(topic: Topic, message: Message, side: Side, sender: Node | None) -> None:
        if side is Side.LAB and topic.name not in IGNORED:
            produced.append(Entry(topic.name, message.stamp_ns, message.cdr()))

    graph.taps.append(tap)
    client = graph.create_node("/replay_client", side=Side.CLIENT)
    watcher = graph.create_node("/replay_watcher")
    publishers: dict[str, Any] = {}
    watched: set[str] = set()
    verdict = Verdict()
    try:
        robot.publish()  # tick 0, as a trial does once its recorder listens
        for render in renderers:
            render(robot.sim.physics, 0)
        ticks = ticks_of(path, frozenset(commands), frozenset(robot.publishers))
        for index, tick in enumerate(_readable(ticks, robot)):
            if index > 0:
                produced.clear()
            needed = {m.topic for m in tick.observed if m.topic in on_demand} - watched
            for topic in needed:  # render cameras from here on, as the record has them
                watcher.subscribe(topic, None, _ignore, hidden=True)
                watched.add(topic)
            if index > 0 and not robot.sim.running:
                # Commands sent after the episode's end (a controller that stepped once
                # more and was told the episode had ended): the lab stepped no more.
                if tick.observed:
                    first = tick.observed[0]
                    verdict.divergence = Divergence(
                        robot.sim.tick, first.topic, first.log_time, "recorded after the end"
                    )
                    return verdict
                break
            if index > 0:
                for command in tick.commands:
                    if command.topic in commands:
                        _send(graph, client, publishers, command)
                robot.step()
                verdict.ticks += 1
                for render in renderers:
                    render(robot.sim.physics, robot.sim.tick)
            found = _compare(tick.observed, produced, on_demand, robot.sim.tick)
            verdict.compared += len(tick.observed)
            if found is not None:
                verdict.divergence = found
                return verdict
            produced.clear()
    finally:
        graph.taps.remove(tap)
    return verdict


def _readable(ticks: Iterator[_Tick], robot: Any) -> Iterator[_Tick]:
    """The record's ticks; a file that stops making sense is a ``ReplayError`` naming
    the last tick read whole."""
    try:
        yield from ticks
    except (McapError, ZstdError, struct.error, EOFError, ValueError) as err:
        raise ReplayError(
            f"the record is cut short or damaged after tick {robot.sim.tick}: {err}"
        ) from None


def _ignore(_message: Message) -> None:
    """The replay's own camera subscription: it makes the robot render; the tap compares."""


def _send(graph: Any, client: Any, publishers: dict[str, Any], command: RecordedMessage) -> None:
    schema = command.schema
    if schema is None:
        raise ReplayError(f"a message on {command.topic} has no schema in the record")
    publisher = publishers.get(command.topic)
    if publisher is None:
        publisher = publishers[command.topic] = client.advertise(command.topic, schema.name)
    codec = graph.codec(schema.name)
    value = codec.from_rosbags(codec.type_store.deserialize_cdr(command.data, schema.name))
    publisher.publish(value)


def _compare(
    recorded: list[RecordedMessage], produced: list[Entry], on_demand: set[str], tick: int
) -> Divergence | None:
    rendered = {(e.topic, e.log_time): e for e in produced if e.topic in on_demand}
    stream = [e for e in produced if e.topic not in on_demand]
    position = 0
    for message in recorded:
        expected = Entry(message.topic, message.log_time, message.data, message.schema)
        if message.topic in on_demand:
            got = rendered.get((message.topic, message.log_time))
        else:
            got = stream[position] if position < len(stream) else None
            position += 1
        what = _differs(expected, got)
        if what is not None:
            return Divergence(tick, message.topic, message.log_time, what)
    if position < len(stream):
        extra = stream[position]
        what = "the replay published a message the record does not have"
        return Divergence(tick, extra.topic, extra.log_time, what)
    return None


def _differs(expected: Entry, got: Entry | None) -> str | None:
    """How a replayed message differs from the recorded one, in words; None if not."""
    if got is None:
        return "the replay has no such message"
    if got.topic != expected.topic:
        return f"the replay has {got.topic} there"
    if got == expected:
        return None
    found = field_difference(expected, Entry(got.topic, got.log_time, got.data, expected.schema))
    if found is None:
        return "the messages differ"
    return found.replace(" in a, ", " recorded, ").replace(" in b", " replayed")


def replay_filed(
    path: Path,
    out: Path,
    types: TypeRegistry | None = None,
    *,
    video: bool = False,
    fps: float = 10.0,
) -> Replayed:
    """Replay a filed record: the verdict as JSON, and with ``video`` its task's first
    camera rendered at ``fps`` into ``out/video.mp4`` (None if none was made).

    What is done after filing every trial (the verdict, by a worker) and for its page
    (the video, by the service's renderer): a record that cannot be replayed (an older
    labd's, another model) is a verdict saying why, not an exception.
    """
    renderers: list[Video] = []
    if video:
        renderers.append(Video(VideoSpec(FIRST, fps=fps, **_camera_size(path)), out / VIDEO))
    try:
        verdict = replay(path, types, renderers=renderers)
        body = {**verdict.to_json(), "said": str(verdict)}
    except LabError as err:  # not replayable here (another model, simulator, task): say so
        body = {**Verdict().to_json(), "verified": False, "said": str(err)}
    finally:
        for renderer in renderers:
            renderer.close()
    made = None
    body["video"] = None
    for renderer in renderers:
        if renderer.frames > 0 and renderer.out.exists():
            made = renderer.out
            body["video"] = {"camera": renderer.camera, "frames": renderer.frames, "fps": fps}
    return Replayed(
        verdict=json.dumps(body, sort_keys=True).encode(),  # as replay.json always was
        verified=bool(body["verified"]),
        video=made,
    )


def _camera_size(path: Path) -> dict[str, int]:
    try:
        manifest = _manifest(path)
    except ReplayError:
        manifest = None
    params = {} if manifest is None else manifest.parameters
    width, height = int(params.get("camera_width", 320)), int(params.get("camera_height", 240))
    return {"width": width - width % 2, "height": height - height % 2}
