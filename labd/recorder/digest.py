"""The data digest of a record, and where two records part.

The data digest decides whether a rerun reproduced a trial. It is sha256 over
``DIGEST_TAG`` followed, for each message on a digest topic (the task's observation and
command topics, ``/clock`` and ``/lab/episode``) in recording order, by::

    u32le(len(topic)) || topic (UTF-8) || u64le(log_time) || u64le(len(cdr)) || cdr

Each variable-length field comes after its length, so two different streams never frame
to the same bytes; the tag names this framing should it ever change. Log times are
simulation times and the data are CDR bytes, so a rerun of the same commit, task,
parameters and seed gives the same digest, bit for bit.

The side that published a message is not part of the framing: on the digest topics it
follows from the topic (the lab publishes the observations, ``/clock`` and
``/lab/episode``, which the graph refuses to clients; clients publish the commands),
and leaving it out keeps the digests of records made before sides were recorded.

``data_digest`` recomputes it from a file; ``first_difference`` walks two records side by
side and returns the first message that differs, with the control tick it belongs to, so
a rerun can report "diverged at tick k on topic t".
"""

from __future__ import annotations

import hashlib
import itertools
import logging
import struct
from collections.abc import Collection, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mcap.records import Schema
from mcap.well_known import MessageEncoding
from mcap_ros2.decoder import DecoderFactory

from labd.recorder.reader import RecordedMessage, read_messages
from repository.well_known import CLOCK, EPISODE

DIGEST_TAG = b"labd data digest 1\n"
log = logging.getLogger("labd.recorder.digest")

_TOPIC = struct.Struct("<I")  # topic name length
_FRAME = struct.Struct("<QQ")  # log time, data length


def topic_frame(topic: str) -> bytes:
    """The framed topic name, which starts each message's bytes in the digest."""
    name = topic.encode()
    return _TOPIC.pack(len(name)) + name


def time_frame(log_time: int, size: int) -> bytes:
    """The framed log time and data length, which follow the topic name."""
    return _FRAME.pack(log_time, size)


def digest_topics(observations: Iterable[str], commands: Iterable[str]) -> list[str]:
    """The topics a record's data digest covers: its task's observations and commands,
    the clock and the episode's ticks; sorted. A batch trial's and a live drive's alike."""
    return sorted({*observations, *commands, CLOCK, EPISODE})


def data_digest(path: str | Path, digest_topics: Collection[str]) -> str:
    """The data digest of a record (its folder or MCAP file), as its Recorder computed it."""
    digest = hashlib.sha256(DIGEST_TAG)
    prefixes: dict[str, bytes] = {}
    for topic, _, time, data, _ in read_messages(path, topics=frozenset(digest_topics)):
        prefix = prefixes.get(topic)
        if prefix is None:
            prefix = prefixes[topic] = topic_frame(topic)
        digest.update(prefix + time_frame(time, len(data)))
        digest.update(data)
    return digest.hexdigest()


@dataclass(frozen=True)
class Entry:
    """One message of a digest stream (its schema, to decode it, takes no part in
    comparisons: two records may number the same schema differently)."""

    topic: str
    log_time: int
    data: bytes
    schema: Schema | None = field(default=None, compare=False)


@dataclass(frozen=True)
class Difference:
    """Where two records first part.

    ``index`` counts the messages of the digest stream from 0. ``topic`` and
    ``log_time`` are those of record ``a``'s message there (``b``'s when ``a`` ended
    first). ``tick`` is the control tick whose ``/lab/episode`` was logged at that time
    (for a command: the tick after which it was sent, so it acts in the next step); None
    when the record has no such message. ``a`` and ``b`` are what each record holds
    there, None for a record that had already ended.
    """

    index: int
    topic: str
    log_time: int
    tick: int | None
    a: Entry | None
    b: Entry | None

    @property
    def what(self) -> str:
        """How the two messages differ, in a few words."""
        if self.a is None or self.b is None:
            return f"record {'a' if self.a is None else 'b'} ended before it"
        if self.a.topic != self.b.topic:
            return f"record b has {self.b.topic} there"
        if self.a.log_time != self.b.log_time:
            return f"record b logged it at {self.b.log_time / 1e9:.9f} s"
        return field_difference(self.a, self.b) or "the messages differ"

    def __str__(self) -> str:
        at = f"tick {self.tick}" if self.tick is not None else f"{self.log_time / 1e9:.9f} s"
        return f"diverged at {at} on {self.topic} (message {self.index}): {self.what}"


class _Stream:
    """A record's digest stream in recording order, keeping track of its episode ticks."""

    def __init__(self, path: str | Path, topics: frozenset[str]) -> None:
        self._messages = read_messages(path, topics=topics | {EPISODE})
        self._topics = topics
        self._episode: RecordedMessage | None = None  # the latest /lab/episode read

    def __iter__(self) -> Iterator[Entry]:
        for message in self._messages:
            if message.topic == EPISODE:
                self._episode = message
            if message.topic in self._topics:
                yield Entry(message.topic, message.log_time, message.data, message.schema)

    def tick_at(self, time: int) -> int | None:
        """The tick of the episode message logged at ``time``, reading on if need be.

        A tick's observations come before its ``/lab/episode``, which may lie ahead.
        """
        while self._episode is None or self._episode.log_time < time:
            message = next(self._messages, None)
            if message is None:
                break
            if message.topic == EPISODE:
                self._episode = message
        if self._episode is None or self._episode.log_time != time:
            return None
        decoder = DecoderFactory().decoder_for(MessageEncoding.CDR, self._episode.schema)
        return None if decoder is None else int(decoder(self._episode.data).tick)

    def close(self) -> None:
        self._messages.close()


def field_difference(a: Entry, b: Entry) -> str | None:
    """The first field where two messages of one topic differ, with both values:
    ``pose.pose.position.x is 1.25 in a, 1.2500001 in b``; None if they cannot be read."""
    if a.schema is None or b.schema is None:
        return None
    factory = DecoderFactory()
    decode_a = factory.decoder_for(MessageEncoding.CDR, a.schema)
    decode_b = factory.decoder_for(MessageEncoding.CDR, b.schema)
    if decode_a is None or decode_b is None:
        return None
    try:
        found = _first_field(decode_a(a.data), decode_b(b.data), "")
    except Exception:  # a message that does not decode: say less, never fail the verdict
        log.debug("could not decode %s to compare it", a.topic, exc_info=True)
        return None
    if found is None:
        return None
    path, x, y = found
    return f"{path or 'the message'} is {_show(x)} in a, {_show(y)} in b"


def _first_field(x: Any, y: Any, path: str) -> tuple[str, Any, Any] | None:
    if hasattr(x, "__slots__") and type(x) is type(y):
        for name in x.__slots__:
            found = _first_field(getattr(x, name), getattr(y, name), f"{path}.{name}".lstrip("."))
            if found:
                return found
        return None
    if isinstance(x, list | tuple) and isinstance(y, list | tuple):
        if len(x) != len(y):
            return (f"{path} (length)", len(x), len(y))
        for i, (u, v) in enumerate(zip(x, y, strict=True)):
            found = _first_field(u, v, f"{path}[{i}]")
            if found:
                return found
        return None
    if isinstance(x, bytes | bytearray) and isinstance(y, bytes | bytearray):
        if x == y:
            return None
        at = next((i for i, (u, v) in enumerate(zip(x, y, strict=False)) if u != v), None)
        return (f"{path} (byte {at if at is not None else min(len(x), len(y))})", len(x), len(y))
    return None if x == y else (path, x, y)


def _show(value: Any) -> str:
    return repr(value) if not isinstance(value, float) else f"{value!r}"


def first_difference(
    a: str | Path, b: str | Path, digest_topics: Collection[str]
) -> Difference | None:
    """The first message where the digest streams of two records differ; None if identical.

    Records (folders or MCAP files) are compared in recording order, the order the digest
    covers, which within an episode is the order of log times.
    """
    topics = frozenset(digest_topics)
    streams = _Stream(a, topics), _Stream(b, topics)
    try:
        for index, (x, y) in enumerate(itertools.zip_longest(*streams)):
            if x == y:
                continue
            where, stream = (x, streams[0]) if x is not None else (y, streams[1])
            assert where is not None
            tick = stream.tick_at(where.log_time)
            return Difference(index, where.topic, where.log_time, tick, x, y)
        return None
    finally:
        for stream in streams:
            stream.close()
