"""Records as data for learning: one row per control tick, in a stable layout per task.

**Ticks.** The lab runs in lockstep: after control tick k it publishes that tick's
observations, then ``/lab/episode`` (tick k); the controller publishes its commands and
calls ``/lab/step``; the lab applies them, advances to tick k+1 and publishes again. A
record keeps that order, and this module reads it in that order (not by log time, since
a tick's commands share its time). Row k of an episode pairs:

- *observation*: the task's observation entries as they stood at tick k (the newest
  message of each topic up to ``/lab/episode`` tick k), and the camera's image of tick k;
- *action*: the command entries in effect during the step from tick k to k+1. A
  command holds until replaced, as the robot holds it; an entry whose topic had no
  message yet has its documented **neutral** value (the robot's own state before any
  command: at rest, the start pose), so there is a row from tick 0 whichever topics a
  controller used;
- *next*: what that step produced, from ``/lab/episode`` tick k+1: ``next.reward``,
  ``next.done`` (the episode ended with it), ``next.success``.

An episode whose last tick is T has rows 0 .. T-1, one per step, checked: a record
that skips a tick is refused. The last observation (tick T) has no step after it and
makes no row. The tick going back (a live robot's reset) starts a new episode.

**Layout.** What the rows hold is the task's ``Layout`` (``labd.sim.features`` defines
one per task; docs/tasks.md lists every entry): the same named float32 entries in the
same order for every trial of the task, whatever topics a controller used, so exports
of different controllers and demonstrations merge. Entries are computed from messages
(a field, a yaw from a quaternion, the goal in the robot's frame ...); nothing that is
constant by construction is an entry. Observations are what the lab published (the
``labd.side`` of their channel is ``lab``); commands are read from either side, since a
live robot's watchdog sends its stops itself. Each episode also has an instruction in
words (``Layout.instruction``, from its first tick's messages) and the provenance of
its record (trial, repository, commit, manifest digest, data digest, ...).

**Cameras.** A camera is recorded as JPEG only while a client subscribed to it. Where
the record has no image for a tick (tick 0, before the controller subscribed; or a
controller that never looked), ``Source.render`` supplies it: the lab replays the record
and renders that camera after the fact (``labd.exports``). So every row has its image.

**Formats.** How rows are written is an ``ExportFormat``: one object, in the module
that writes it, declaring its name, its media type, the names of its files and its
writer; ``repository.formats`` lists them (``repository.parquet``,
``repository.lerobot``). The archive, the API, the pages and the ``labd`` command ask
that list, so a format is added in one place.

Errors are ``ExportError``; the output folder appears whole or not at all.
"""

from __future__ import annotations

import json
import logging
import shutil
import struct
import uuid
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mcap.exceptions import McapError
from mcap_ros2.decoder import DecoderFactory
from zstandard import ZstdError

from repository.errors import ExportError
from repository.mcapfile import messages
from repository.trial import EpisodeStatus
from repository.well_known import EPISODE, SIDE_KEY

IMAGES = "observation.images."  # a camera's feature: observation.images.<name>
_UNREADABLE = (McapError, OSError, ValueError, EOFError, IndexError, struct.error, ZstdError)

log = logging.getLogger("repository.export")

Messages = Mapping[str, Any]  # topic -> the newest decoded message
Extract = Callable[[Messages, str], float | None]


@dataclass(frozen=True)
class Entry:
    """One named float of an observation or action vector.

    ``extract(messages, topic)`` computes it when a message arrives on one of its
    ``topics`` (``topic`` says which; ``messages`` holds the newest of each): a number,
    or None to keep the value it had (a trajectory that does not name this joint).
    Before any message it is ``neutral``.
    """

    name: str
    topics: tuple[str, ...]
    extract: Extract
    neutral: float = 0.0
    unit: str = ""
    doc: str = ""


@dataclass(frozen=True)
class Camera:
    """A camera of the task: its feature is ``observation.images.<name>``."""

    name: str
    topic: str  # sensor_msgs/msg/CompressedImage, JPEG


@dataclass(frozen=True)
class Layout:
    """A task's rows: observation entries, action entries, cameras, the instruction."""

    task: str
    version: str
    observation: tuple[Entry, ...]
    action: tuple[Entry, ...]
    cameras: tuple[Camera, ...]
    instruction: Callable[[Messages], str]  # from the messages of an episode's first tick
    instruction_topics: tuple[str, ...] = ()  # the topics it reads

    @property
    def observation_topics(self) -> frozenset[str]:
        return frozenset(t for e in self.observation for t in e.topics)

    @property
    def action_topics(self) -> frozenset[str]:
        return frozenset(t for e in self.action for t in e.topics)

    def describe(self) -> dict[str, Any]:
        """The layout as JSON, for an export's metadata."""
        return {
            "task": self.task,
            "version": self.version,
            "observation": [e.name for e in self.observation],
            "action": [e.name for e in self.action],
            "cameras": {c.name: c.topic for c in self.cameras},
        }


Render = Callable[[Sequence[int]], Mapping[int, bytes]]  # ticks -> JPEG of each


@dataclass(frozen=True)
class Source:
    """One record to export: its MCAP file, its provenance (JSON), and how to render a
    camera's missing frames (``render(camera, ticks)``: JPEG per tick), if it can be."""

    mcap: Path
    provenance: Mapping[str, Any]
    render: Callable[[str, Sequence[int]], Mapping[int, bytes]] | None = None


@dataclass
class Episode:
    """One episode's rows."""

    provenance: dict[str, Any]
    instruction: str
    ticks: list[int] = field(default_factory=list)
    times: list[int] = field(default_factory=list)  # ns, simulation time of each row's tick
    state: list[list[float]] = field(default_factory=list)
    action: list[list[float]] = field(default_factory=list)
    reward: list[float] = field(default_factory=list)
    done: list[bool] = field(default_factory=list)
    success: list[bool] = field(default_factory=list)
    images: dict[str, list[bytes | None]] = field(default_factory=dict)
    rendered: dict[str, int] = field(default_factory=dict)  # camera -> frames rendered
    last_tick: int = 0  # the episode's last tick (T): rows are 0 .. T-1

    def __len__(self) -> int:
        return len(self.ticks)


Writer = Callable[[Sequence[Episode], Layout, Path], list[Path]]  # -> the files written


@dataclass(frozen=True)
class ExportFormat:
    """One export format: what the archive, the API, the pages and the command need of it.

    ``write(episodes, layout, folder)`` writes the rows into the empty ``folder`` and
    returns the files written; ``frames(folder)`` and ``episodes(folder)`` count the
    rows and episodes of an export read back. One trial's export is served as the file
    ``served`` of its folder, or, where ``served`` is None, as a zip of the folder.
    """

    name: str  # as a URL and ``labd export --format`` spell it
    title: str  # a download's name on a page
    doc: str  # what it is, in a few words
    media_type: str  # of one trial's export, as served
    suffix: str  # ends a download's name: trial-12.parquet, trial-12-lerobot.zip
    served: str | None
    write: Writer
    frames: Callable[[Path], int]
    episodes: Callable[[Path], int]

    @property
    def artifact(self) -> str:
        """The name of one trial's export among its record's derived artifacts."""
        return f"export{self.suffix}"

    def filename(self, trial: int) -> str:
        """The name of one trial's export, downloaded."""
        return f"trial-{trial}{self.suffix}"


@dataclass(frozen=True)
class ExportSummary:
    """What an export wrote."""

    format: str  # its ExportFormat's name
    out: Path
    files: tuple[Path, ...]
    frames: int
    episodes: int
    observation_names: tuple[str, ...]
    action_names: tuple[str, ...]
    cameras: tuple[str, ...]
    rendered: int  # camera frames the lab rendered because the record had none


def export(
    sources: Sequence[Source], out: Path, fmt: ExportFormat, layout: Layout
) -> ExportSummary:
    """Export the records ``sources``, one or more episodes each, to the folder ``out``
    in the format ``fmt`` (``repository.formats``); ``out`` must not exist or be an
    empty folder. ExportError for what cannot be exported.
    """
    if not sources:
        raise ExportError("there is no record to export")
    for source in sources:
        try:
            json.dumps(dict(source.provenance), allow_nan=False)
        except (TypeError, ValueError) as err:
            raise ExportError(f"the provenance must be JSON: {err}") from None
    out = Path(out)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise ExportError(f"{out} already exists: give a new or empty folder")
    episodes = [e for source in sources for e in read_episodes(source, layout)]
    tmp = out.parent / f".{out.name}.{uuid.uuid4().hex}.tmp"
    tmp.mkdir(parents=True)
    try:
        files = fmt.write(episodes, layout, tmp)
        if out.exists():
            out.rmdir()
        tmp.rename(out)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)  # gone already unless something failed
    summary = ExportSummary(
        format=fmt.name,
        out=out,
        files=tuple(out / f.relative_to(tmp) for f in files),
        frames=sum(len(e) for e in episodes),
        episodes=len(episodes),
        observation_names=tuple(e.name for e in layout.observation),
        action_names=tuple(e.name for e in layout.action),
        cameras=tuple(c.name for c in layout.cameras),
        rendered=sum(n for e in episodes for n in e.rendered.values()),
    )
    log.info(
        "exported %d rows of %d episodes as %s to %s (%d camera frames rendered)",
        summary.frames,
        summary.episodes,
        fmt.name,
        out,
        summary.rendered,
    )
    return summary


# -- reading ---------------------------------------------------------------------------


class _Reader:
    """Turns a record's messages, in recording order, into episodes of rows."""

    def __init__(self, layout: Layout, provenance: Mapping[str, Any]) -> None:
        self.layout = layout
        self.provenance = dict(provenance)
        self.cameras = {c.topic: c.name for c in layout.cameras}
        self.latest: dict[str, Any] = {}
        self.state = [e.neutral for e in layout.observation]
        self.action = [e.neutral for e in layout.action]
        self.by_topic_obs = _by_topic(layout.observation)
        self.by_topic_act = _by_topic(layout.action)
        self.images: dict[str, bytes] = {}  # this tick's
        self.pending: tuple[int, int, list[float], dict[str, bytes]] | None = None
        self.episodes: list[Episode] = []
        self.current: Episode | None = None

    def observe(self, topic: str, message: Any) -> None:
        self.latest[topic] = message
        if topic in self.cameras:
            self.images[self.cameras[topic]] = bytes(message.data)
        for i in self.by_topic_obs.get(topic, ()):
            value = self.layout.observation[i].extract(self.latest, topic)
            if value is not None:
                self.state[i] = float(value)

    def command(self, topic: str, message: Any) -> None:
        self.latest[topic] = message
        for i in self.by_topic_act.get(topic, ()):
            value = self.layout.action[i].extract(self.latest, topic)
            if value is not None:
                self.action[i] = float(value)

    def tick(self, time_ns: int, message: Any) -> None:
        tick = int(message.tick)
        pending = self.pending
        if pending is not None and tick == pending[0] + 1 and self.current is not None:
            then, then_ns, state, images = pending
            episode = self.current
            episode.ticks.append(then)
            episode.times.append(then_ns)
            episode.state.append(state)
            episode.action.append(list(self.action))
            episode.reward.append(float(message.reward))
            episode.done.append(str(message.status) != EpisodeStatus.RUNNING)
            episode.success.append(bool(message.success))
            for camera in self.layout.cameras:
                episode.images[camera.name].append(images.get(camera.name))
        elif pending is not None and tick == pending[0]:
            pass  # the same tick published again (a latched repeat): its newest state counts
        elif pending is None or tick < pending[0]:  # the first tick, or a new episode
            self._start(tick)
        else:
            assert self.current is not None
            raise ExportError(
                f"the record skips from tick {pending[0]} to tick {tick}: it is not whole"
            )
        assert self.current is not None
        self.current.last_tick = tick
        self.pending = (tick, time_ns, list(self.state), dict(self.images))
        self.images = {}

    def _start(self, tick: int) -> None:
        if tick != 0:
            raise ExportError(f"an episode of the record starts at tick {tick}, not 0")
        self.action = [e.neutral for e in self.layout.action]
        provenance = dict(self.provenance)
        provenance["episode_in_record"] = len(self.episodes)
        self.current = Episode(
            provenance=provenance,
            instruction=self.layout.instruction(self.latest),
            images={c.name: [] for c in self.layout.cameras},
        )
        self.episodes.append(self.current)


def _by_topic(entries: Sequence[Entry]) -> dict[str, list[int]]:
    found: dict[str, list[int]] = {}
    for i, entry in enumerate(entries):
        for topic in entry.topics:
            found.setdefault(topic, []).append(i)
    return found


def read_episodes(source: Source, layout: Layout) -> list[Episode]:
    """The episodes of one record, every row with its image (see the module's docstring)."""
    path = Path(source.mcap)
    if not path.is_file():
        raise ExportError(f"no MCAP file at {path}")
    reader = _Reader(layout, source.provenance)
    observed = layout.observation_topics | {c.topic for c in layout.cameras}
    commanded = layout.action_topics
    observed |= frozenset(layout.instruction_topics)
    decoders: dict[int, Callable[[bytes], Any] | None] = {}
    factory = DecoderFactory()
    try:
        with path.open("rb") as stream:
            for schema, channel, message in messages(stream):
                topic = channel.topic
                if channel.id not in decoders:
                    side = channel.metadata.get(SIDE_KEY)
                    lab = side in (None, "lab")
                    wanted = ((topic in observed or topic == EPISODE) and lab) or topic in commanded
                    decoders[channel.id] = (
                        factory.decoder_for(channel.message_encoding, schema) if wanted else None
                    )
                decode = decoders[channel.id]
                if decode is None:
                    continue
                value = decode(message.data)
                if topic == EPISODE:
                    reader.tick(message.log_time, value)
                elif topic in commanded:
                    reader.command(topic, value)
                else:
                    reader.observe(topic, value)
    except _UNREADABLE as err:
        reason = f"{type(err).__name__}: {err}" if str(err) else type(err).__name__
        raise ExportError(f"{path} is not a complete, readable MCAP file ({reason})") from None
    episodes = [e for e in reader.episodes if len(e)]
    if not episodes:
        raise ExportError(f"{path} has no control tick followed by a step: nothing to export")
    for episode in episodes:
        if episode.ticks != list(range(episode.last_tick)):
            raise ExportError(f"{path}: rows do not match the record's ticks")
        _fill_images(source, episode)
    return episodes


def _fill_images(source: Source, episode: Episode) -> None:
    """Every row's image: the record's, else the lab's rendering of that tick."""
    for camera, images in episode.images.items():
        missing = [episode.ticks[i] for i, image in enumerate(images) if image is None]
        if not missing:
            continue
        if source.render is None:
            raise ExportError(
                f"{source.mcap} has no image of {camera} for {len(missing)} ticks"
                f" (from tick {missing[0]}), and nothing can render them"
            )
        frames = source.render(camera, missing)
        for i, tick in enumerate(episode.ticks):
            if images[i] is None:
                if tick not in frames:
                    raise ExportError(f"the replay rendered no image of {camera} at tick {tick}")
                images[i] = frames[tick]
        episode.rendered[camera] = len(missing)
