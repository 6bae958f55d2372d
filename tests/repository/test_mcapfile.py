"""Reading MCAP files within limits: the same messages as mcap's reader, and no part of a
file larger than the limit ever held, whatever the file declares."""

from __future__ import annotations

import struct
import tracemalloc
from pathlib import Path

import pytest
from mcap.reader import NonSeekingReader
from mcap.records import Chunk
from mcap.writer import CompressionType, Writer

from repository.mcapfile import RecordFileError, messages, open_chunk, records
from tests.helpers.records import chunk_record, with_chunk, zstd_bomb

MiB = 1 << 20


def small_record(path: Path, attachment: bytes = b"") -> Path:
    """An MCAP file of 50 messages on two topics, in small zstd chunks."""
    with path.open("wb") as out:
        writer = Writer(out, chunk_size=1024, compression=CompressionType.ZSTD)
        writer.start()
        schema = writer.register_schema("t/msg/M", "ros2msg", b"int32 x")
        channels = [writer.register_channel(t, "cdr", schema) for t in ("/a", "/b")]
        for n in range(50):
            writer.add_message(channels[n % 2], n, n.to_bytes(4, "little") * 40, n)
        if attachment:
            writer.add_attachment(0, 0, "big.bin", "application/octet-stream", attachment)
        writer.finish()  # type: ignore[no-untyped-call]
    return path


def test_messages_are_mcaps_own(tmp_path):
    """``messages`` gives what mcap's NonSeekingReader gives, in order, and by topic."""
    path = small_record(tmp_path / "r.mcap")
    with path.open("rb") as a, path.open("rb") as b:
        ours = [(c.topic, m.log_time, m.data) for _, c, m in messages(a)]
        theirs = [
            (c.topic, m.log_time, m.data)
            for _, c, m in NonSeekingReader(b).iter_messages(log_time_order=False)
        ]
    assert ours == theirs and len(ours) == 50
    with path.open("rb") as a:
        assert [m.log_time for _, _, m in messages(a, {"/b"})] == list(range(1, 50, 2))


def test_a_chunk_declaring_more_than_the_limit_is_refused_unread(tmp_path):
    """A chunk of a few KiB declaring 64 MiB, with a 1 MiB limit, is refused before a
    byte is decompressed, and says how much it declared and the limit."""
    bomb = zstd_bomb(64 * MiB)
    path = with_chunk(
        small_record(tmp_path / "r.mcap"), tmp_path / "b.mcap", chunk_record(bomb, 64 * MiB)
    )
    tracemalloc.start()
    try:
        with path.open("rb") as stream, pytest.raises(RecordFileError) as caught:
            list(messages(stream, limit=MiB))
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert "a chunk declares 64 MiB decompressed, over the limit of 1 MiB" in str(caught.value)
    assert peak < 4 * MiB


def test_a_chunk_holding_more_than_it_declares_is_refused_at_the_declared_size(tmp_path):
    """A chunk declaring 1 KiB that decompresses to 64 MiB is refused having held no
    more than what it declared (and one byte)."""
    bomb = zstd_bomb(64 * MiB)
    path = with_chunk(
        small_record(tmp_path / "r.mcap"), tmp_path / "b.mcap", chunk_record(bomb, 1024)
    )
    tracemalloc.start()
    try:
        with path.open("rb") as stream, pytest.raises(RecordFileError) as caught:
            list(records(stream))
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert "declares 1,024 bytes decompressed and holds 1,025" in str(caught.value)
    assert peak < 4 * MiB


def test_a_record_longer_than_the_limit_is_refused(tmp_path):
    """An attachment of 2 MiB, with a 1 MiB limit, is refused; chunks left closed are
    never decompressed, so a manifest search skips them."""
    path = small_record(tmp_path / "r.mcap", attachment=bytes(2 * MiB))
    with path.open("rb") as stream, pytest.raises(RecordFileError, match="at most 1 MiB"):
        list(records(stream, limit=MiB))
    bomb = zstd_bomb(64 * MiB)
    bombed = with_chunk(path, tmp_path / "b.mcap", chunk_record(bomb, 64 * MiB))
    with bombed.open("rb") as stream:
        assert all(type(r).__name__ != "Message" for r in records(stream, chunks=False))


def test_open_chunk_refuses_other_compressions():
    """A chunk in a compression the lab never writes is refused by name."""
    chunk = Chunk(
        compression="lz4", data=b"1234", message_start_time=0, message_end_time=0,
        uncompressed_crc=0, uncompressed_size=4,
    )  # fmt: skip
    with pytest.raises(RecordFileError, match="compressed with 'lz4'"):
        open_chunk(chunk)


def test_a_chunk_cut_inside_a_record_is_refused():
    """A chunk whose last record runs past its end, or ends inside a record's header,
    or holds a message too short to have its fields, is refused as damaged; a whole one
    reads, skipping a kind of record a chunk should not hold."""

    def chunk(data: bytes) -> Chunk:
        return Chunk(
            compression="", data=data, message_start_time=0, message_end_time=0,
            uncompressed_crc=0, uncompressed_size=len(data),
        )  # fmt: skip

    message = struct.pack("<BQHIQQ", 5, 22 + 3, 1, 7, 100, 100) + b"abc"
    footer = struct.pack("<BQ", 2, 1) + b"\0"  # a footer: not a chunk's, skipped
    (read,) = open_chunk(chunk(message + footer))
    assert (read.channel_id, read.sequence, read.log_time, read.data) == (1, 7, 100, b"abc")
    for damaged, said in (
        (message[:-1], "runs past the end"),
        (message + b"\5\0", "inside a record's header"),
        (struct.pack("<BQ", 5, 4) + b"abcd", "too short"),
    ):
        with pytest.raises(RecordFileError, match=said):
            open_chunk(chunk(damaged))
