"""Recording a graph: every message of every topic into one MCAP file (ROS 2 profile).

The ``Recorder`` is a graph tap, so it sees each message delivered on any topic, in
delivery order, and writes it at once:

- one schema per message type (``ros2msg``: the full definition text with its
  dependencies, as rosbag2 writes it) and one channel per topic and side of the bridge
  that published on it (``cdr``, with the QoS and type hash rosbag2 puts in its
  metadata, and the side under ``labd.side``: ``lab`` or ``client``), registered at
  their first message. A topic has two channels only where both sides published
  (``/rosout``); the robot's topics are the lab's alone (the graph refuses clients
  there), so a reader tells observations from actions by the side (``reader``);
- each message is its CDR bytes (``Message.cdr()``, encoded once and shared with whoever
  else needs them); log time = publish time = the message's graph stamp, which in trials
  is simulation time; sequence numbers count per channel;
- zstd-compressed chunks of about a megabyte, with MCAP's indexes and statistics;
- the manifest as a metadata record named ``manifest`` holding one key, ``json``: the
  manifest's canonical JSON (``repository.digests``), whose sha256 is the manifest digest.
  Metadata values must be strings and a manifest nests (parameters), so one JSON text
  keeps it whole, where a flattening would have to be undone by every reader;
- the attachments given to ``finish`` (model, ``lab.toml``, controller logs ...), logged
  at the last message's time;
- the bag information as the ``rosbag2`` metadata record, as rosbag2's MCAP storage does.

A record is whole or it is not there. When the disk refuses a write (it is full), the
recorder stops recording, deletes what it had written, and ``finish`` raises
``RecordError`` saying so; the graph and its robot carry on undisturbed, since the
error never reaches the publisher whose message was being written.

A recorder given ``keep`` records only the messages it accepts, told each one's topic,
side and publishing node: a live robot's drive keeps the robot's and its driver's
(``labd.live``), so that no one watching writes into the driver's record.

It runs on every control tick in the lab's event loop, so the per-message work is a
dictionary look-up, the library's ``add_message`` and, for digest topics, two hash
updates; compression happens once a chunk is full. A recorder made with ``defer``
(a trial's) keeps what it is told during a callback of the event loop and writes it
just after: a lockstep tick's observations are encoded and written once the tick's
answer has left for the controller, while the controller decides its next command,
rather than before. The same messages are written in the same order.

The data digest is over topics, not sides, as it was before records kept sides, so
earlier records still compare with their reruns: a client's message can reach a digest
topic only where the lab does not publish (a command), since the graph refuses clients
the lab's topics.
"""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import json
import logging
from collections.abc import Callable, Collection, Mapping
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any, Self

from mcap.records import Metadata
from mcap.well_known import MessageEncoding, Profile, SchemaEncoding
from mcap.writer import CompressionType, Writer

from labd.errors import RecordError
from labd.graph.graph import Graph, Node, Side, Topic
from labd.graph.message import Message
from labd.recorder import bag
from labd.recorder.digest import DIGEST_TAG, time_frame, topic_frame
from repository.digests import canonical_json
from repository.mcapfile import records
from repository.units import MiB
from repository.well_known import MANIFEST_KEY, MANIFEST_RECORD, RECORD_FILE, SIDE_KEY

CHUNK_SIZE = MiB  # bytes: minutes of state, or seconds of camera frames, per chunk
_SEQUENCE = 0xFFFF_FFFF  # MCAP sequence numbers are uint32


MEDIA_TYPES = {
    ".png": "image/png",
    ".jpg": "image/jpeg",
    ".jpeg": "image/jpeg",
    ".xml": "application/xml",
    ".json": "application/json",
    ".toml": "application/toml",
    ".log": "text/plain",
    ".txt": "text/plain",
    ".stl": "model/stl",
    ".obj": "model/obj",
}


def media_type(name: str) -> str:
    """The media type of an attachment, by its name's suffix (unknown: octet-stream)."""
    suffix = name[name.rfind(".") :].lower() if "." in name else ""
    return MEDIA_TYPES.get(suffix, "application/octet-stream")


def read_manifest(path: str | Path) -> dict[str, Any] | None:
    """The manifest stored in a record (its folder or MCAP file); None if it has none.

    The recorder writes it first, so the file is read from its start only as far as the
    manifest: a record cut short later still names what it was. Chunks are skipped
    unopened (a manifest is never in one), each read within ``repository.mcapfile``'s
    limit.
    """
    with bag.mcap_path(path).open("rb") as stream:
        for record in records(stream, chunks=False):
            if isinstance(record, Metadata) and record.name == MANIFEST_RECORD:
                value: dict[str, Any] = json.loads(record.metadata[MANIFEST_KEY])
                return value
    return None


@dataclass(frozen=True)
class RecordSummary:
    """What a finished record holds.

    ``start_time`` and ``end_time`` are the first and last log times, in nanoseconds
    (simulation time in trials); None when nothing was recorded.
    """

    path: Path  # the MCAP file
    counts: Mapping[str, int]  # messages per topic
    data_digest: str  # sha256, hex (see labd.recorder.digest)
    start_time: int | None
    end_time: int | None
    size: int  # bytes of the MCAP file

    @property
    def folder(self) -> Path:
        return self.path.parent

    @property
    def message_count(self) -> int:
        return sum(self.counts.values())


class _Channel:
    """A topic as one side published it: its MCAP channel, count, and what the bag says."""

    __slots__ = ("count", "id", "latched", "prefix", "topic", "type_hash", "type_name")

    def __init__(
        self, id_: int, topic: str, *, type_name: str, type_hash: str, latched: bool, digest: bool
    ) -> None:
        self.id = id_
        self.topic = topic
        self.type_name = type_name
        self.type_hash = type_hash
        self.latched = latched
        self.count = 0
        self.prefix = topic_frame(topic) if digest else None  # None: not in the digest


# Whether a message is to be recorded, told its topic, itself, and its publisher's side
# and node (a live robot's record keeps the robot's and its driver's, nobody else's).
Keep = Callable[[Topic, Message, Side, Node | None], bool]


class Recorder:
    """Records every message of ``graph`` into ``folder/trial.mcap`` until ``finish``.

    ``digest_topics`` are the topics the data digest covers; ``keep``, when given,
    decides which messages are recorded at all. The folder is created if need be; a
    record already in it is never overwritten (``FileExistsError``). Call ``finish``
    in a ``finally``, or use the recorder as a context manager, so the file is complete
    even when the controller crashed; ``discard`` when the record is not wanted.
    """

    def __init__(
        self,
        graph: Graph,
        folder: str | Path,
        *,
        digest_topics: Collection[str],
        manifest: Mapping[str, Any] | None = None,
        chunk_size: int = CHUNK_SIZE,
        keep: Keep | None = None,
        defer: bool = False,
    ) -> None:
        self.graph = graph
        self.folder = Path(folder)
        self.path = self.folder / RECORD_FILE
        self.digest_topics = frozenset(digest_topics)
        self.keep = keep
        self.log = logging.getLogger(f"labd.recorder.{graph.name}")
        manifest_text = None if manifest is None else canonical_json(manifest)  # fail early
        self.folder.mkdir(parents=True, exist_ok=True)
        self._file = self.path.open("xb")
        self._error: OSError | None = None  # the write that failed: the record is gone
        # Checksums of every chunk and of the whole data section, so a reader can tell a
        # damaged file (``mcap doctor``, the reader's validate_crcs) without the archive.
        self._writer = Writer(
            self._file,
            chunk_size=chunk_size,
            compression=CompressionType.ZSTD,
            enable_crcs=True,
            enable_data_crcs=True,
        )
        self._schemas: dict[str, int] = {}
        self._lab_channels: dict[Topic, _Channel] = {}  # by side: no enum hash per message
        self._client_channels: dict[Topic, _Channel] = {}
        # A topic made anew keeps its channels: by name, type and side.
        self._by_key: dict[tuple[str, str, Side], _Channel] = {}
        self._digest = hashlib.sha256(DIGEST_TAG)
        self._start = 1 << 64
        self._end = -1
        self._has_manifest = False
        self._summary: RecordSummary | None = None
        # (topic, message, side) told but not written yet: written by ``settle``
        self._pending: list[tuple[Topic, Message, Side]] | None = [] if defer else None
        try:
            self._writer.start(profile=Profile.ROS2)
            if manifest_text is not None:
                self._write_manifest(manifest_text)
        except OSError as err:
            self._fail(err)
            raise RecordError(self.path, err) from err
        graph.taps.append(self._tap)

    # -- recording ---------------------------------------------------------------------

    def _tap(self, topic: Topic, message: Message, side: Side, sender: Node | None) -> None:
        if self._error is not None:
            return
        if self.keep is not None and not self.keep(topic, message, side, sender):
            return
        pending = self._pending
        if pending is None:
            self._write(topic, message, side)
            return
        if not pending:
            try:
                loop = asyncio.get_running_loop()
            except RuntimeError:  # no event loop: at once
                self._write(topic, message, side)
                return
            # Two turns of the loop: the first lets what this callback made ready (the
            # bridge's write of the tick's answer) go first.
            loop.call_soon(loop.call_soon, self.settle)
        pending.append((topic, message, side))

    def settle(self) -> None:
        """Write what was told and kept for later (``defer``)."""
        pending = self._pending
        if not pending:
            return
        self._pending = []
        for topic, message, side in pending:
            if self._error is not None:
                return
            self._write(topic, message, side)

    def _write(self, topic: Topic, message: Message, side: Side) -> None:
        channels = self._lab_channels if side is Side.LAB else self._client_channels
        data = message.cdr()
        time = message.stamp_ns
        try:
            channel = channels.get(topic)
            if channel is None:
                channel = self._channel(topic, side)
            self._writer.add_message(channel.id, time, data, time, channel.count & _SEQUENCE)
        except OSError as err:  # the disk is full: the record is lost, the robot goes on
            self._fail(err)
            return
        channel.count += 1
        if channel.prefix is not None:
            self._digest.update(channel.prefix + time_frame(time, len(data)))
            self._digest.update(data)
        self._end = max(self._end, time)
        self._start = min(self._start, time)

    def _channel(self, topic: Topic, side: Side) -> _Channel:
        key = (topic.name, topic.type_name, side)
        channel = self._by_key.get(key)
        if channel is None:
            types = self.graph.types
            type_name = topic.type_name
            schema = self._schemas.get(type_name)
            if schema is None:
                text = types.definition_text(type_name).encode()
                schema = self._writer.register_schema(type_name, SchemaEncoding.ROS2, text)
                self._schemas[type_name] = schema
            latched = any(p.latch for p in topic.publishers if p.side is side)
            type_hash = types.typestore.hash_rihs01(type_name)
            metadata = {**bag.channel_metadata(type_hash, latched), SIDE_KEY: side.value}
            channel_id = self._writer.register_channel(
                topic.name, MessageEncoding.CDR, schema, metadata
            )
            channel = _Channel(
                channel_id,
                topic.name,
                type_name=type_name,
                type_hash=type_hash,
                latched=latched,
                digest=topic.name in self.digest_topics,
            )
            self._by_key[key] = channel
        channels = self._lab_channels if side is Side.LAB else self._client_channels
        channels[topic] = channel
        return channel

    def _write_manifest(self, text: str) -> None:
        self._writer.add_metadata(MANIFEST_RECORD, {MANIFEST_KEY: text})
        self._has_manifest = True

    @property
    def data_digest(self) -> str:
        """The digest of what has been recorded so far."""
        self.settle()
        return self._digest.hexdigest()

    @property
    def size(self) -> int:
        """Bytes of the file so far: what is written, without the chunk being filled
        (at most ``chunk_size`` bytes before compression, or one larger message)."""
        if self._summary is not None:
            return self._summary.size
        self.settle()
        if self._file.closed:
            return 0
        return self._file.tell()

    @property
    def counts(self) -> dict[str, int]:
        """Messages recorded so far, per topic."""
        self.settle()
        counts: dict[str, int] = {}
        for channel in self._by_key.values():
            counts[channel.topic] = counts.get(channel.topic, 0) + channel.count
        return counts

    # -- finishing ---------------------------------------------------------------------

    def finish(
        self,
        attachments: Mapping[str, tuple[str, bytes]] | None = None,
        *,
        manifest: Mapping[str, Any] | None = None,
    ) -> RecordSummary:
        """Stop recording, add the manifest and attachments, complete the file and the bag.

        ``attachments`` maps names to ``(media_type, data)``. ``manifest`` is for a
        recorder made without one; a second manifest is a ValueError, raised once the
        file is complete all the same. Calling again returns the same summary.
        ``RecordError`` if the record could not be written (it was deleted).
        """
        if self._summary is not None:
            return self._summary
        if self._tap in self.graph.taps:
            self.graph.taps.remove(self._tap)
        self.settle()
        if self._error is not None:
            raise RecordError(self.path, self._error)
        try:
            try:
                if manifest is not None:
                    if self._has_manifest:
                        raise ValueError("the record already has its manifest")
                    self._write_manifest(canonical_json(manifest))
                for name, (media_type, data) in (attachments or {}).items():
                    # create_time 0 is MCAP's "unknown": records hold no wall-clock time.
                    self._writer.add_attachment(0, max(self._end, 0), name, media_type, data)
            finally:
                self._summary = self._complete()
        except OSError as err:
            self._summary = None
            self._fail(err)
            raise RecordError(self.path, err) from err
        return self._summary

    def discard(self) -> None:
        """Stop recording and delete the record: one that will not be filed."""
        if self._tap in self.graph.taps:
            self.graph.taps.remove(self._tap)
        if self._pending is not None:
            self._pending = []
        with contextlib.suppress(OSError):
            self._file.close()
            self.path.unlink(missing_ok=True)
            (self.folder / bag.BAG_METADATA).unlink(missing_ok=True)

    def _fail(self, err: OSError) -> None:
        """A write failed: stop recording and delete the record, which cannot be whole."""
        self._error = err  # the tap stays (it may be iterated now) but writes nothing more
        with contextlib.suppress(OSError):
            self._file.close()  # what it still held cannot be written either
        self.path.unlink(missing_ok=True)
        (self.folder / bag.BAG_METADATA).unlink(missing_ok=True)
        self.log.error("the record %s could not be written and was deleted: %s", self.path, err)

    def _complete(self) -> RecordSummary:
        """Write the bag record and the summary section, close the file, write the bag."""
        # rosbag2 knows topics, not sides: the bag lists each topic once (per type and
        # QoS, which rosbags matches channels by), with both sides' messages.
        merged: dict[tuple[str, str, bool], bag.BagTopic] = {}
        for c in self._by_key.values():
            key = (c.topic, c.type_name, c.latched)
            count = c.count + (merged[key].message_count if key in merged else 0)
            merged[key] = bag.BagTopic(c.topic, c.type_name, c.type_hash, c.latched, count)
        topics = list(merged.values())
        info = bag.to_yaml(bag.bag_info(topics, self._start, self._end))  # YAML is slow: once
        try:
            self._writer.add_metadata(bag.BAG_RECORD, {bag.BAG_RECORD_KEY: info})
            self._writer.finish()  # type: ignore[no-untyped-call]
        finally:
            self._file.close()
        bag.write_bag_yaml(self.folder, info)
        counts = self.counts
        summary = RecordSummary(
            path=self.path,
            counts=counts,
            data_digest=self.data_digest,
            start_time=self._start if counts else None,
            end_time=self._end if counts else None,
            size=self.path.stat().st_size,
        )
        self.log.info(
            "recorded %d messages on %d topics, %d bytes, in %s; data digest %s",
            summary.message_count,
            len(counts),
            summary.size,
            self.path,
            summary.data_digest,
        )
        return summary

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        self.finish()
