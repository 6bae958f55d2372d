"""The op families of the protocol, one module each, registered in ``CAPABILITIES``.

Each declares a ``Handler`` per op it takes (``Capability.handlers``); the session
dispatches through one table made from those declarations. Tests reach a session's
family by its class: ``session.capability(Fragments)``.
"""

from __future__ import annotations

from collections.abc import Callable

from labd.bridge.ops.actions import Actions
from labd.bridge.ops.fragments import Fragments
from labd.bridge.ops.services import Services
from labd.bridge.ops.status import Status
from labd.bridge.ops.topics import Topics
from labd.bridge.session import Capability, Session

CAPABILITIES: list[Callable[[Session], Capability]] = [Topics, Services, Actions, Status, Fragments]

__all__ = ["CAPABILITIES"]
