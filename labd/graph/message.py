"""A message in flight: its type, its value in normal form, and its renderings.

One ``Message`` is shared by every subscriber of a topic. Each rendering (JSON,
CBOR, CDR) is made the first time someone needs it and kept, so a message that a
hundred browsers receive is encoded once.
"""

from __future__ import annotations

from typing import Any

import cbor2

from labd.graph.codec import Codec, dumps


class Message:
    """An immutable, validated message. Build it with ``Codec`` or ``Graph`` helpers."""

    __slots__ = ("_cbor", "_cdr", "_json", "codec", "data", "stamp_ns")

    def __init__(self, codec: Codec, data: dict[str, Any], stamp_ns: int = 0) -> None:
        self.codec = codec
        self.data = data  # normal form; never mutated once published
        self.stamp_ns = stamp_ns  # graph time when it was published
        self._json: bytes | None = None
        self._cbor: Any = None
        self._cdr: bytes | None = None

    @property
    def type_name(self) -> str:
        return self.codec.type.name

    def json(self) -> bytes:
        """The JSON text of the value (the ``msg`` of a publish frame)."""
        if self._json is None:
            self._json = dumps(self.data)
        return self._json

    def cbor_value(self) -> Any:
        """The value with numeric arrays as RFC 8746 typed arrays, ready for cbor2."""
        if self._cbor is None:
            self._cbor = self.codec.to_cbor(self.data)
        return self._cbor

    def cdr(self) -> bytes:
        """The CDR (little-endian) serialization, as ROS 2 and MCAP carry it."""
        if self._cdr is None:
            self._cdr = self.codec.to_cdr(self.data)
        return self._cdr

    def size_hint(self) -> int:
        """Bytes this message holds while it waits in an outgoing queue.

        Its JSON, plus, for a message with ``uint8[]`` data, the decoded bytes, which
        are three quarters of their base64 text: an estimate that errs high.
        """
        size = len(self.json())
        return size + size * 3 // 4 if self.codec.has_binary else size

    def __repr__(self) -> str:
        return f"Message({self.type_name}, {self.data!r})"


def cbor_frame(frame: dict[str, Any]) -> bytes:
    """Encode a whole frame as CBOR (for subscribers that asked for ``cbor``)."""
    return cbor2.dumps(frame)
