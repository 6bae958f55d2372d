"""Reading a record: its channels, and its messages by topic and by side.

A record has one MCAP channel per topic and side of the bridge that published on it
(``labd.graph.Side``), named in the channel's metadata under ``SIDE_KEY``: ``lab`` for
what the lab published (a robot's observations, ``/tf``, ``/clock``, ``/lab/episode``,
the lab's ``/rosout`` lines), ``client`` for what a bridge client published (a
controller's commands, a page's ``/ux/events``, its ``/rosout`` lines). So a reader
tells observations from actions without knowing the task::

    for message in read_messages(path, side=Side.CLIENT):   # what the controller did
        print(message.topic, message.log_time)

A topic that both sides published on (``/rosout``) has two channels. Records made
before sides were kept have none in their metadata: their channels' side is None, and
a side filter leaves them out.

Records are read within the archive's limits (``repository.mcapfile``): a file whose
chunk or record is over ``MAX_PART`` is a ``RecordFileError``, never a reader holding
what the file declares.
"""

from __future__ import annotations

from collections.abc import Collection, Generator, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

from mcap.records import Attachment, Channel, Schema

from labd.graph.graph import Side
from labd.recorder.bag import mcap_path
from repository.mcapfile import messages, seeking
from repository.well_known import SIDE_KEY

_SIDES = {side.value: side for side in Side}


def side_of(channel: Channel) -> Side | None:
    """The side that published on ``channel``; None in a record that does not say."""
    return _SIDES.get(channel.metadata.get(SIDE_KEY, ""))


@dataclass(frozen=True)
class RecordedChannel:
    """One channel of a record: a topic as one side published it."""

    id: int
    topic: str
    type_name: str  # the schema's name, e.g. nav_msgs/msg/Odometry
    side: Side | None
    message_count: int


class RecordedMessage(NamedTuple):
    """One message of a record, in recording order."""

    topic: str
    side: Side | None
    log_time: int  # nanoseconds: simulation time in trials
    data: bytes  # CDR
    schema: Schema | None


def read_channels(path: str | Path) -> list[RecordedChannel]:
    """The channels of a finished record (its folder or MCAP file), by channel id."""
    with mcap_path(path).open("rb") as stream:
        summary = seeking(stream).get_summary()
    if summary is None:
        raise ValueError(f"{path} has no summary section: the record was not finished")
    counts = summary.statistics.channel_message_counts if summary.statistics else {}
    return [
        RecordedChannel(
            channel.id,
            channel.topic,
            summary.schemas[channel.schema_id].name if channel.schema_id in summary.schemas else "",
            side_of(channel),
            counts.get(channel.id, 0),
        )
        for channel in sorted(summary.channels.values(), key=lambda c: c.id)
    ]


def read_attachments(path: str | Path) -> Iterator[Attachment]:
    """The attachments of a finished record (its folder or MCAP file), one at a time, by
    the summary's index; each one read within the archive's limit."""
    with mcap_path(path).open("rb") as stream:
        yield from seeking(stream).iter_attachments()


def read_messages(
    path: str | Path, *, topics: Collection[str] | None = None, side: Side | None = None
) -> Generator[RecordedMessage, None, None]:
    """The messages of a record in the order they were written, which needs no summary.

    ``topics`` keeps those topics only; ``side`` keeps what that side published.
    """
    sides: dict[int, Side | None] = {}
    with mcap_path(path).open("rb") as stream:
        for schema, channel, message in messages(stream, topics):
            if channel.id not in sides:
                sides[channel.id] = side_of(channel)
            channel_side = sides[channel.id]
            if side is not None and channel_side is not side:
                continue
            yield RecordedMessage(
                channel.topic, channel_side, message.log_time, message.data, schema
            )
