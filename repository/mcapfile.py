"""Reading a record's MCAP file within limits, whoever made the file.

mcap's own readers trust what a file declares. A chunk says how many bytes it
decompresses to, and the reader allocates that much at once; a record's length is
read into memory up to 4 GiB. So a chunk of 64 KiB that decompresses to 2 GiB of zeros
(zstd packs them that tightly) takes 2 GiB from whoever reads it, and a reader with
less memory dies of a ``MemoryError``.

Here every record of a file is read with ``MAX_PART`` as the bound on its length, and a
chunk's declared size is checked against the same bound before anything is
decompressed. Decompressing then streams and stops at the declared size, so a chunk
that holds more than it declares is refused too. Nothing larger than ``MAX_PART`` is
ever held. The lab writes chunks of about 1 MiB and attachments of a few MiB (a
controller's output is capped at 8 MiB), so the bound leaves room for any record the
lab made. A file over it is a ``RecordFileError`` naming the part and the limit.

    with path.open("rb") as stream:
        for schema, channel, message in messages(stream, topics={"/odom"}):
            ...
"""

from __future__ import annotations

import io
import struct
from collections.abc import Collection, Iterator
from typing import IO

import zstandard
from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError, RecordLengthLimitExceeded
from mcap.opcode import Opcode
from mcap.reader import SeekingReader
from mcap.records import Channel, Chunk, McapRecord, Message, Schema
from mcap.stream_reader import StreamReader

from repository.errors import ArchiveError
from repository.units import MiB

MAX_PART = 256 * MiB  # bytes: the most one record of a file, or one chunk decompressed, may hold
_PIECE = MiB  # bytes decompressed at a time


class RecordFileError(ArchiveError, McapError):
    """An MCAP file whose parts are over the limit, or not what they declare.

    It is an ``McapError`` too, so whoever already reports an unreadable MCAP file
    reports this one the same way.
    """


def mib(size: int) -> str:
    """A size in MiB, as the limit is documented: ``2048 MiB``."""
    return f"{size / MiB:.0f} MiB" if size >= MiB else f"{size:,} bytes"


def records(
    stream: IO[bytes], *, chunks: bool = True, limit: int = MAX_PART
) -> Iterator[McapRecord]:
    """The records of the file in order, as mcap's ``StreamReader`` gives them, each
    chunk opened into its records (``chunks=False``: chunks left closed, unread)."""
    reader = StreamReader(stream, emit_chunks=True, record_size_limit=limit)
    try:
        for record in reader.records:
            if not isinstance(record, Chunk):
                yield record
            elif chunks:
                yield from open_chunk(record, limit)
    except RecordLengthLimitExceeded as err:
        raise RecordFileError(
            f"{err}: one record of a file may hold at most {mib(limit)}"
        ) from None


def open_chunk(chunk: Chunk, limit: int = MAX_PART) -> list[McapRecord]:
    """The records in ``chunk``, refused unread if it declares more than ``limit`` bytes
    and refused if it decompresses to other than it declares."""
    declared = chunk.uncompressed_size
    if declared > limit:
        raise RecordFileError(
            f"a chunk declares {mib(declared)} decompressed, over the limit of {mib(limit)}"
            " for one part of a record: the file is not a record the lab made, or was damaged"
        )
    if chunk.compression == "zstd":
        data = _zstd(chunk.data, declared)
    elif chunk.compression == "":
        data = chunk.data
    else:
        raise RecordFileError(
            f"a chunk is compressed with {chunk.compression!r}; the lab reads zstd or none"
        )
    if len(data) != declared:
        raise RecordFileError(
            f"a chunk declares {declared:,} bytes decompressed and holds {len(data):,}:"
            " the file was damaged or made to mislead"
        )
    return _chunk_records(data)


_HEAD = struct.Struct("<BQ")  # a record's opcode and length
_MESSAGE = struct.Struct("<HIQQ")  # channel id, sequence, log time, publish time


def _chunk_records(data: bytes) -> list[McapRecord]:
    """The records of a chunk's decompressed bytes.

    Messages, nearly all of a chunk, are read here with one ``struct`` call each (mcap's
    own reader takes a method call per field: a fifth of a replay); schemas and channels
    by mcap's classes. A record that runs past the chunk's end is a ``RecordFileError``.
    """
    out: list[McapRecord] = []
    view = memoryview(data)
    position, end = 0, len(data)
    head, body, message = _HEAD.size, _MESSAGE.size, Opcode.MESSAGE
    while position < end:
        if position + head > end:
            raise RecordFileError("a chunk ends inside a record's header: the file was damaged")
        opcode, length = _HEAD.unpack_from(data, position)
        start = position + head
        position = start + length
        if position > end:
            raise RecordFileError("a record runs past the end of its chunk: the file was damaged")
        if opcode == message:
            if length < body:
                raise RecordFileError("a message record is too short: the file was damaged")
            channel_id, sequence, log_time, publish_time = _MESSAGE.unpack_from(data, start)
            out.append(
                Message(channel_id, log_time, bytes(view[start + body : position]), publish_time,
                        sequence)
            )  # fmt: skip
        elif opcode in (Opcode.CHANNEL, Opcode.SCHEMA):
            stream = ReadDataStream(io.BytesIO(view[start:position]))
            out.append(Channel.read(stream) if opcode == Opcode.CHANNEL else Schema.read(stream))
        # any other record in a chunk is skipped, as mcap's reader does
    return out


def _zstd(data: bytes, declared: int) -> bytes:
    """Decompress up to one byte past ``declared``: enough to know it holds more."""
    parts: list[bytes] = []
    size = 0
    try:
        with zstandard.ZstdDecompressor().stream_reader(data) as reader:
            while size <= declared:
                piece = reader.read(min(_PIECE, declared + 1 - size))
                if not piece:
                    break
                parts.append(piece)
                size += len(piece)
    except zstandard.ZstdError as err:
        raise RecordFileError(f"a chunk does not decompress: {err}") from None
    return b"".join(parts)


def messages(
    stream: IO[bytes], topics: Collection[str] | None = None, *, limit: int = MAX_PART
) -> Iterator[tuple[Schema | None, Channel, Message]]:
    """The messages of the file in the order they were written, with their channel and
    schema (None for a channel without one), as mcap's ``NonSeekingReader`` gives them;
    ``topics`` keeps those topics only."""
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    wanted = None if topics is None else frozenset(topics)
    for record in records(stream, limit=limit):
        if isinstance(record, Message):
            channel = channels.get(record.channel_id)
            if channel is None:
                raise RecordFileError(f"a message is on channel {record.channel_id}, never made")
            if wanted is None or channel.topic in wanted:
                yield schemas.get(channel.schema_id), channel, record
        elif isinstance(record, Channel):
            channels[record.id] = record
        elif isinstance(record, Schema):
            schemas[record.id] = record


def seeking(stream: IO[bytes], *, limit: int = MAX_PART) -> SeekingReader:
    """mcap's reader of the summary, metadata and attachments by their indexes, with each
    record it reads bounded by ``limit`` (its message reading opens chunks unbounded:
    read messages with ``messages``)."""
    return SeekingReader(stream, record_size_limit=limit)
