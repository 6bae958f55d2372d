"""fragment: reassembly of messages a client sends in parts.

Parts may arrive in any order; a message is handled once all ``total`` parts are
in. Reassembly is bounded: at most ``max_fragmented`` messages at once, at most
``max_message_size`` characters each, and a message whose parts stop coming is
forgotten after ``fragment_timeout`` seconds.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

from labd.bridge.frames import Fragment
from labd.bridge.session import Capability, Handler, Session
from labd.clock import TimerHandle
from labd.errors import FrameError, LimitError


@dataclass
class _Assembly:
    total: int
    timer: TimerHandle
    parts: dict[int, str] = field(default_factory=dict)
    size: int = 0


class Fragments(Capability):
    def __init__(self, session: Session) -> None:
        super().__init__(session)
        self.assemblies: dict[str | int, _Assembly] = {}
        self._depth = 0

    def handlers(self) -> Iterable[Handler[Any]]:
        return (Handler(Fragment, self.fragment),)

    def fragment(self, op: Fragment) -> None:
        config = self.session.config
        if self._depth:
            raise FrameError("fragments may not contain fragments", "fragment")
        if not 0 < op.total <= config.max_message_size or not 0 <= op.num < op.total:
            raise FrameError(
                f"fragment.num must be in 0..total-1 and total positive "
                f"(got num {op.num}, total {op.total})",
                "fragment",
            )
        assembly = self.assemblies.get(op.id)
        if assembly is None:
            if len(self.assemblies) >= config.max_fragmented:
                raise LimitError("messages in fragments at once", config.max_fragmented)
            timer = self.session.timers.call_later(config.fragment_timeout, self._expire, op.id)
            assembly = self.assemblies[op.id] = _Assembly(op.total, timer)
        elif assembly.total != op.total:
            self._discard(op.id)
            raise FrameError(
                f"fragment {op.id!r} changed its total from {assembly.total} to "
                f"{op.total}; the message was dropped",
                "fragment",
            )
        if op.num in assembly.parts:
            return
        assembly.parts[op.num] = op.data
        assembly.size += len(op.data)
        if assembly.size > config.max_message_size:
            self._discard(op.id)
            raise LimitError("characters in one fragmented message", config.max_message_size)
        if len(assembly.parts) < assembly.total:
            return
        self._discard(op.id)
        text = "".join(assembly.parts[i] for i in range(assembly.total))
        self._depth += 1
        try:
            self.session.receive(text)
        finally:
            self._depth -= 1

    def _discard(self, frag_id: str | int) -> None:
        assembly = self.assemblies.pop(frag_id, None)
        if assembly is not None:
            assembly.timer.cancel()

    def _expire(self, frag_id: str | int) -> None:
        assembly = self.assemblies.pop(frag_id, None)
        if assembly is not None:
            self.session.report(
                "warning",
                f"fragment {frag_id!r}: only {len(assembly.parts)} of "
                f"{assembly.total} parts arrived in time; the message was dropped",
            )

    def close(self) -> None:
        for assembly in self.assemblies.values():
            assembly.timer.cancel()
        self.assemblies.clear()
