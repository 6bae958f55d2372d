"""Rendering outgoing frames: JSON, PNG, CBOR, CBOR-raw, and fragmentation.

Every frame the bridge sends is an ``OutFrame``: bytes and whether they go out as a
text frame (JSON) or a binary one (CBOR). Topic messages are rendered late, when the
connection is ready to take them, so a client that falls behind costs a reference
to a shared message, not a copy.
"""

from __future__ import annotations

import base64
import io
import math
from dataclasses import dataclass
from typing import Any

import cbor2
import orjson
from PIL import Image

from labd.graph.codec import dumps
from labd.graph.message import Message

COMPRESSIONS = ("none", "png", "cbor", "cbor-raw")


@dataclass(frozen=True, slots=True)
class OutFrame:
    data: bytes
    text: bool = True

    def __len__(self) -> int:
        return len(self.data)


def json_frame(frame: dict[str, Any]) -> OutFrame:
    return OutFrame(dumps(frame))


def png_encode(text: bytes) -> str:
    """rosbridge's PNG compression: the bytes as a square RGB image, base64.

    The image is padded with newlines, which JSON parsers skip.
    """
    length = max(len(text), 3)
    width = max(1, math.floor(math.sqrt(length / 3.0)))
    height = math.ceil((length / 3.0) / width)
    padded = text + b"\n" * (width * height * 3 - len(text))
    image = Image.frombytes("RGB", (width, height), padded)
    out = io.BytesIO()
    image.save(out, "png")
    return base64.b64encode(out.getvalue()).decode("ascii")


def png_decode(data: str) -> bytes:
    """Inverse of ``png_encode`` (for tests and clients written in Python)."""
    with Image.open(io.BytesIO(base64.b64decode(data))) as image:
        return image.tobytes().rstrip(b"\n")


def finish(
    body: bytes, compression: str, fragment_size: int | None, fragment_id: str
) -> list[OutFrame]:
    """Apply PNG compression and fragmentation to a JSON frame."""
    if compression == "png":
        body = orjson.dumps({"op": "png", "data": png_encode(body)})
    if fragment_size is None or fragment_size <= 0 or len(body) <= fragment_size:
        return [OutFrame(body)]
    return fragment(body.decode("utf-8"), fragment_size, fragment_id)


def fragment(text: str, size: int, fragment_id: str) -> list[OutFrame]:
    """Split a frame's text into ``fragment`` ops whose data parts hold ``size`` characters."""
    pieces = [text[i : i + size] for i in range(0, len(text), size)]
    total = len(pieces)
    return [
        OutFrame(
            orjson.dumps(
                {"op": "fragment", "id": fragment_id, "data": piece, "num": num, "total": total}
            )
        )
        for num, piece in enumerate(pieces)
    ]


class TopicRenderer:
    """Renders messages of one topic for one client, as that client asked."""

    def __init__(self, topic: str, compression: str, fragment_size: int | None) -> None:
        self.topic = topic  # exactly as the client spelled it
        self.compression = compression
        self.fragment_size = fragment_size
        self._prefix = b'{"op":"publish","topic":' + orjson.dumps(topic) + b',"msg":'

    def render(self, message: Message, fragment_id: str) -> list[OutFrame]:
        if self.compression == "cbor":
            frame = {"op": "publish", "topic": self.topic, "msg": message.cbor_value()}
            return [OutFrame(cbor2.dumps(frame), text=False)]
        if self.compression == "cbor-raw":
            sec, nanosec = divmod(message.stamp_ns, 1_000_000_000)
            raw = {"bytes": message.cdr(), "secs": sec, "nsecs": nanosec}
            frame = {"op": "publish", "topic": self.topic, "msg": raw}
            return [OutFrame(cbor2.dumps(frame), text=False)]
        body = self._prefix + message.json() + b"}"
        if self.compression == "none" and (
            self.fragment_size is None or len(body) <= self.fragment_size
        ):
            return [OutFrame(body)]
        return finish(body, self.compression, self.fragment_size, fragment_id)
