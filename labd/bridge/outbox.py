"""A client's bounded outgoing queue.

Everything the bridge sends a client goes through its ``Outbox``, in order: replies
and status frames (*control*) and topic messages. Order matters: in lockstep, the
observations of a tick must reach the controller before the answer to its
``/lab/step`` call.

The queue is bounded, so a slow or stalled client never grows the server's memory
and never slows anyone else:

- each topic stream may hold at most its own number of messages (its
  ``queue_length``, or the default); beyond that its oldest message is dropped;
- all topic messages together may hold at most ``max_bytes``; beyond that the
  oldest topic messages are dropped, whatever their topic;
- control frames are never dropped; if they alone exceed ``max_bytes`` the client
  is not reading at all, and ``overflowed`` tells the session to disconnect it.

Topic messages are rendered only when popped; until then an entry is a reference to
the shared ``Message``.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from typing import Protocol

from labd.bridge.render import OutFrame
from labd.graph.message import Message


class Renders(Protocol):
    """What a topic entry needs from its stream."""

    pending: deque[_Entry]
    dropped: int

    def render(self, message: Message) -> list[OutFrame]: ...


class _Entry:
    __slots__ = ("frame", "message", "size", "stream")

    def __init__(
        self, frame: OutFrame | None, message: Message | None, stream: Renders | None, size: int
    ) -> None:
        self.frame = frame
        self.message = message
        self.stream = stream
        self.size = size


class Outbox:
    """FIFO of frames and topic messages with per-stream and byte limits."""

    def __init__(self, max_bytes: int, wake: Callable[[], None]) -> None:
        self.max_bytes = max_bytes
        self._wake = wake
        self._queue: deque[_Entry] = deque()
        self._dead = 0  # dropped entries still sitting in the deque
        self.topic_bytes = 0
        self.control_bytes = 0
        self.dropped = 0
        self.overflowed = False

    def __len__(self) -> int:
        return len(self._queue) - self._dead

    @property
    def pending_bytes(self) -> int:
        return self.topic_bytes + self.control_bytes

    def push_frame(self, frame: OutFrame) -> None:
        self._push(_Entry(frame, None, None, len(frame)))
        self.control_bytes += len(frame)
        if self.control_bytes > self.max_bytes:
            self.overflowed = True

    def push_message(
        self, stream: Renders, message: Message, limit: int, size: int | None = None
    ) -> None:
        """Queue ``message`` for ``stream``, which holds at most ``limit``; ``size``:
        the bytes it will go out as, when its stream knows (else its JSON's)."""
        if size is None:
            size = message.size_hint()
        entry = _Entry(None, message, stream, size)
        stream.pending.append(entry)
        self.topic_bytes += size
        self._push(entry)
        while len(stream.pending) > limit:
            self._drop(stream.pending[0])
        while self.topic_bytes > self.max_bytes:
            self._drop_oldest_message()

    def discard(self, stream: Renders) -> None:
        """Forget every message waiting for ``stream`` (it was unsubscribed)."""
        while stream.pending:
            self._drop(stream.pending[0], count=False)

    def pop(self) -> list[OutFrame] | None:
        """The frames of the oldest entry, or None if nothing waits."""
        queue = self._queue
        while queue:
            entry = queue.popleft()
            if entry.stream is None and entry.message is None and entry.frame is None:
                self._dead -= 1
                continue
            if entry.frame is not None:
                self.control_bytes -= entry.size
                return [entry.frame]
            stream, message = entry.stream, entry.message
            assert stream is not None and message is not None
            stream.pending.popleft()
            self.topic_bytes -= entry.size
            return stream.render(message)
        return None

    def _push(self, entry: _Entry) -> None:
        was_empty = len(self._queue) == self._dead
        self._queue.append(entry)
        if was_empty:
            self._wake()

    def _drop(self, entry: _Entry, count: bool = True) -> None:
        stream = entry.stream
        assert stream is not None and stream.pending[0] is entry
        stream.pending.popleft()
        if count:
            stream.dropped += 1
            self.dropped += 1
        self.topic_bytes -= entry.size
        entry.stream = entry.message = None
        self._dead += 1
        if self._dead > 1024 and self._dead > len(self._queue) // 2:
            self._compact()

    def _drop_oldest_message(self) -> None:
        for entry in self._queue:
            if entry.message is not None:
                self._drop_head_of(entry)
                return

    def _drop_head_of(self, entry: _Entry) -> None:
        # The oldest live message overall is the oldest of its own stream.
        assert entry.stream is not None
        self._drop(entry.stream.pending[0])

    def _compact(self) -> None:
        self._queue = deque(e for e in self._queue if e.frame is not None or e.message is not None)
        self._dead = 0
