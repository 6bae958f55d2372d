"""Editing a record as someone who wants it to say something else would: with mcap itself.

``rewrite`` copies a record's MCAP file record by record into a new, well-formed file,
changing what it is asked to (an attachment's bytes, a topic left out, an attachment
added); the messages it keeps are the same bytes at the same times, so the manifest and
the data digest stay what they were. ``zstd_bomb`` is a zstd frame of a few KiB that
really decompresses to ``size`` zero bytes, and ``with_chunk`` puts it in a record as a
chunk declaring that size.
"""

from __future__ import annotations

import io
import struct
from collections.abc import Callable, Collection, Mapping
from pathlib import Path

import zstandard
from mcap.records import Attachment, Channel, Message, Metadata, Schema
from mcap.stream_reader import StreamReader
from mcap.well_known import Profile
from mcap.writer import CompressionType, Writer

GiB = 1 << 30


def rewrite(
    source: Path,
    dest: Path,
    *,
    attachments: Mapping[str, Callable[[bytes], bytes]] | None = None,
    drop: Collection[str] = (),
    add: Mapping[str, bytes] | None = None,
) -> Path:
    """Copy the record ``source`` to ``dest``: each attachment named in ``attachments``
    passed through its function, the topics in ``drop`` left out, ``add``'s attachments
    added at the end."""
    edits = dict(attachments or {})
    schemas: dict[int, int] = {}
    channels: dict[int, int] = {}
    with source.open("rb") as stream, dest.open("wb") as out:
        writer = Writer(out, compression=CompressionType.ZSTD)
        writer.start(profile=Profile.ROS2, library="an editor")
        for record in StreamReader(stream).records:
            if isinstance(record, Schema):
                schemas[record.id] = writer.register_schema(
                    record.name, record.encoding, record.data
                )
            elif isinstance(record, Channel) and record.topic not in drop:
                channels[record.id] = writer.register_channel(
                    record.topic,
                    record.message_encoding,
                    schemas.get(record.schema_id, 0),
                    dict(record.metadata),
                )
            elif isinstance(record, Message) and record.channel_id in channels:
                writer.add_message(
                    channels[record.channel_id],
                    record.log_time,
                    record.data,
                    record.publish_time,
                    record.sequence,
                )
            elif isinstance(record, Metadata):
                writer.add_metadata(record.name, dict(record.metadata))
            elif isinstance(record, Attachment):
                data = edits.get(record.name, lambda d: d)(record.data)
                writer.add_attachment(
                    record.create_time, record.log_time, record.name, record.media_type, data
                )
        for name, data in (add or {}).items():
            writer.add_attachment(0, 0, name, "application/octet-stream", data)
        writer.finish()  # type: ignore[no-untyped-call]
    return dest


def zstd_bomb(size: int) -> bytes:
    """A zstd frame that decompresses to ``size`` zero bytes (2 GiB: about 64 KiB)."""
    compressor = zstandard.ZstdCompressor(level=1).compressobj()
    piece = bytes(16 << 20)
    parts = []
    left = size
    while left:
        take = min(left, len(piece))
        parts.append(compressor.compress(piece[:take] if take < len(piece) else piece))
        left -= take
    parts.append(compressor.flush())
    return b"".join(parts)


def chunk_record(compressed: bytes, declared: int) -> bytes:
    """An MCAP Chunk record (opcode 0x06) holding ``compressed`` (zstd), declaring that it
    decompresses to ``declared`` bytes."""
    compression = b"zstd"
    body = (
        struct.pack("<QQQI", 0, 0, declared, 0)
        + struct.pack("<I", len(compression))
        + compression
        + struct.pack("<Q", len(compressed))
        + compressed
    )
    return struct.pack("<BQ", 0x06, len(body)) + body


def with_chunk(source: Path, dest: Path, chunk: bytes) -> Path:
    """``source`` with ``chunk`` inserted right after its header record, where a reader
    meets it before anything else (the manifest included)."""
    data = source.read_bytes()
    stream = io.BytesIO(data)
    stream.seek(8)  # the magic
    opcode, length = struct.unpack("<BQ", stream.read(9))
    assert opcode == 0x01, "an MCAP file starts with its header record"
    at = 8 + 9 + length
    dest.write_bytes(data[:at] + chunk + data[at:])
    return dest
