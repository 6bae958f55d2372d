"""Foxglove's WebSocket protocol on the wire: the frames a client sends, parsed once
at the edge, and the binary frames the lab sends.

The protocol (``foxglove.websocket.v1``, and ``foxglove.sdk.v1``, the same protocol
under the name the Foxglove SDK's servers use) has JSON text frames with an ``op``
and binary frames that begin with a one-byte opcode; integers are little-endian.
A client subscribes to channels and advertises its own by numeric ids, so no op
names a topic: the session maps ids to names.

``parse_text`` turns a text frame into one of the ``ClientOp`` structs below (or a
``FrameError`` that names the op and the field); ``parse_binary`` turns a binary
frame into ``ClientData`` (a message on a client channel) or ``ServiceRequest``.
``{"op": "auth", "key": ...}`` is the lab's, as on rosbridge: the protocol has no
way to present a key of its own.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import Any

import msgspec

from labd.bridge.frames import Auth, Op, op_named
from labd.bridge.render import OutFrame
from labd.errors import FrameError

SDK = "foxglove.sdk.v1"  # the Foxglove SDK's servers, and so today's app
WEBSOCKET = "foxglove.websocket.v1"  # the spec's name; @foxglove/ws-protocol's client
SUBPROTOCOLS = (SDK, WEBSOCKET)  # in the order the lab prefers them

# Binary opcodes, server to client.
MESSAGE_DATA = 0x01
TIME = 0x02
SERVICE_CALL_RESPONSE = 0x03
# Binary opcodes, client to server.
CLIENT_MESSAGE_DATA = 0x01
SERVICE_CALL_REQUEST = 0x02
PLAYBACK_CONTROL = 0x03  # foxglove.sdk.v1 only; the lab plays nothing back

_MESSAGE_HEAD = struct.Struct("<BIQ")
_TIME = struct.Struct("<BQ")
_CALL_HEAD = struct.Struct("<BIII")
_U32 = struct.Struct("<I")


def select(offered: list[str] | tuple[str, ...]) -> str | None:
    """The subprotocol the lab answers a client that offers ``offered``: Foxglove's,
    the SDK's name first (as the SDK chooses it), or None for rosbridge."""
    for name in SUBPROTOCOLS:
        if name in offered:
            return name
    return None


# -- client to server, text ---------------------------------------------------------------


class SubscriptionRequest(msgspec.Struct, frozen=True):
    id: int
    channelId: int


class Subscribe(Op, frozen=True, tag="subscribe"):
    subscriptions: list[SubscriptionRequest]


class Unsubscribe(Op, frozen=True, tag="unsubscribe"):
    subscriptionIds: list[int]


class ClientChannel(msgspec.Struct, frozen=True):
    id: int
    topic: str
    encoding: str
    schemaName: str
    schema: str | None = None  # the client's definition; the lab uses its own
    schemaEncoding: str | None = None


class Advertise(Op, frozen=True, tag="advertise"):
    channels: list[ClientChannel]


class Unadvertise(Op, frozen=True, tag="unadvertise"):
    channelIds: list[int]


class GetParameters(Op, frozen=True, tag="getParameters"):
    parameterNames: list[str] = msgspec.field(default_factory=list)
    id: str | None = None


class Parameter(msgspec.Struct, frozen=True):
    name: str
    value: Any = None
    type: str | None = None


class SetParameters(Op, frozen=True, tag="setParameters"):
    parameters: list[Parameter]
    id: str | None = None


class SubscribeParameterUpdates(Op, frozen=True, tag="subscribeParameterUpdates"):
    parameterNames: list[str] = msgspec.field(default_factory=list)


class UnsubscribeParameterUpdates(Op, frozen=True, tag="unsubscribeParameterUpdates"):
    parameterNames: list[str] = msgspec.field(default_factory=list)


class SubscribeConnectionGraph(Op, frozen=True, tag="subscribeConnectionGraph"):
    pass


class UnsubscribeConnectionGraph(Op, frozen=True, tag="unsubscribeConnectionGraph"):
    pass


class FetchAsset(Op, frozen=True, tag="fetchAsset"):
    uri: str
    requestId: int


ClientOp = (
    Auth
    | Subscribe
    | Unsubscribe
    | Advertise
    | Unadvertise
    | GetParameters
    | SetParameters
    | SubscribeParameterUpdates
    | UnsubscribeParameterUpdates
    | SubscribeConnectionGraph
    | UnsubscribeConnectionGraph
    | FetchAsset
)
OPS = frozenset(t.__struct_config__.tag for t in ClientOp.__args__)
_decoder = msgspec.json.Decoder(ClientOp)


def parse_text(text: str | bytes) -> Op:
    """One text frame as an op; FrameError says what is wrong with it."""
    try:
        return _decoder.decode(text)  # type: ignore[no-any-return]
    except msgspec.DecodeError as err:
        raise _explain(text, str(err)) from None


def _explain(text: str | bytes, message: str) -> FrameError:
    op = op_named(text)
    if isinstance(op, FrameError):
        return op
    if op not in OPS:
        return FrameError(f"{op!r} is not an op of Foxglove's protocol that the lab takes")
    # msgspec: "Expected `int`, got `str` - at `$.subscriptions[0].id`"
    where = message.rsplit(" - at `$", 1)
    field = where[1].rstrip("`").lstrip(".") if len(where) == 2 else ""
    what = where[0].replace("`", "")
    return FrameError(f"{op}{'.' + field if field else ''}: {what[0].lower()}{what[1:]}")


# -- client to server, binary ---------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class ClientData:
    """A message on a channel the client advertised."""

    channel: int
    payload: bytes


@dataclass(frozen=True, slots=True)
class ServiceRequest:
    """A call of an advertised service, in ``encoding``."""

    service: int
    call: int
    encoding: str
    payload: bytes


def parse_binary(data: bytes) -> ClientData | ServiceRequest:
    """One binary frame; FrameError for one the lab does not take."""
    if not data:
        raise FrameError("an empty binary frame")
    opcode = data[0]
    if opcode == CLIENT_MESSAGE_DATA:
        if len(data) < 5:
            raise FrameError(f"a message frame of {len(data)} bytes has no channel id")
        return ClientData(_U32.unpack_from(data, 1)[0], data[5:])
    if opcode == SERVICE_CALL_REQUEST:
        if len(data) < _CALL_HEAD.size:
            raise FrameError(f"a service call frame of {len(data)} bytes is cut short")
        _, service, call, length = _CALL_HEAD.unpack_from(data)
        start = _CALL_HEAD.size
        if len(data) < start + length:
            raise FrameError("a service call frame's encoding runs past its end")
        try:
            encoding = data[start : start + length].decode()
        except UnicodeDecodeError:
            raise FrameError("a service call frame's encoding is not UTF-8") from None
        return ServiceRequest(service, call, encoding, data[start + length :])
    if opcode == PLAYBACK_CONTROL:
        raise FrameError("playback control: a live robot plays nothing back")
    raise FrameError(f"binary opcode 0x{opcode:02x} is not one the lab takes")


# -- server to client -----------------------------------------------------------------------


def message_data(subscription: int, log_ns: int, payload: bytes) -> OutFrame:
    return OutFrame(_MESSAGE_HEAD.pack(MESSAGE_DATA, subscription, log_ns) + payload, text=False)


def time_frame(ns: int) -> OutFrame:
    return OutFrame(_TIME.pack(TIME, ns), text=False)


def service_call_response(service: int, call: int, encoding: str, payload: bytes) -> OutFrame:
    name = encoding.encode()
    head = _CALL_HEAD.pack(SERVICE_CALL_RESPONSE, service, call, len(name))
    return OutFrame(head + name + payload, text=False)


def service_call_request(service: int, call: int, encoding: str, payload: bytes) -> bytes:
    """A client's call (for tests and clients written in Python)."""
    name = encoding.encode()
    return _CALL_HEAD.pack(SERVICE_CALL_REQUEST, service, call, len(name)) + name + payload


def client_message(channel: int, payload: bytes) -> bytes:
    """A client's message on its channel (for tests and clients written in Python)."""
    return bytes([CLIENT_MESSAGE_DATA]) + _U32.pack(channel) + payload
