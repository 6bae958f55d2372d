"""Foxglove's WebSocket protocol on the lab's bridge, beside rosbridge on the same port.

A client that offers ``foxglove.sdk.v1`` or ``foxglove.websocket.v1`` as its WebSocket
subprotocol gets a ``FoxgloveSession``; every other client gets rosbridge v2.
"""

from labd.bridge.foxglove.session import FoxgloveSession, ServerInfo
from labd.bridge.foxglove.wire import SUBPROTOCOLS, select

__all__ = ["SUBPROTOCOLS", "FoxgloveSession", "ServerInfo", "select"]
