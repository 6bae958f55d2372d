"""set_level.

Status frames go only to a client that asked for them with ``set_level``: rosbridge
clients such as roslibpy fail on an ``op`` they did not expect. An ``auth`` frame on a
connection already open never reaches a capability: the session answers it itself.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

from labd.bridge.frames import SetLevel
from labd.bridge.session import LEVELS, Capability, Handler


class Status(Capability):
    def handlers(self) -> Iterable[Handler[Any]]:
        return (Handler(SetLevel, self.set_level),)

    def set_level(self, op: SetLevel) -> None:
        level = LEVELS.get(op.level)
        if level is None:
            # The protocol says a bad level is dropped; say so to the log only.
            self.session.log.info(
                "client %d: set_level %r is not one of %s",
                self.session.client_id,
                op.level,
                ", ".join(LEVELS),
            )
            return
        self.session.status_level = level
        self.session.report("info", f"status level set to {op.level}", op.id)
