"""set_level, and auth frames that arrive once a connection is already open.

Status frames go only to a client that asked for them with ``set_level``: rosbridge
clients such as roslibpy fail on an ``op`` they did not expect.
"""

from __future__ import annotations

from labd.bridge.frames import Auth, Op, SetLevel
from labd.bridge.session import LEVELS, Capability


class Status(Capability):
    ops = (SetLevel, Auth)

    def handle(self, op: Op) -> None:
        if isinstance(op, SetLevel):
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
        elif isinstance(op, Auth):
            self.session.report("info", "auth: this connection needs no (further) authorization")
