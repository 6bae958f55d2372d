"""Incoming rosbridge frames, parsed once at the edge into typed operations.

``parse`` turns the text of one WebSocket frame into one of the ``Op`` structs below,
or raises ``FrameError`` with a sentence that names the op and the field
(``subscribe.throttle_rate must be a number, got a string``). Handlers never look
into raw JSON. Fields that clients send but the lab has no use for (``latch`` on
subscribe, ``queue_size`` on advertise, ``type`` on call_service) are ignored, as
rosbridge ignores them.
"""

from __future__ import annotations

import re
from typing import Any

import msgspec
import orjson

from labd.errors import FrameError
from labd.graph.codec import describe

Id = str | int | None


class Op(msgspec.Struct, frozen=True, tag_field="op"):
    """Base of every operation a client may send."""


class Auth(Op, frozen=True, tag="auth"):
    key: str | None = None
    mac: str | None = None  # rosauth's field; roslibjs' authenticate() sends it


class SetLevel(Op, frozen=True, tag="set_level"):
    level: str
    id: Id = None


class Fragment(Op, frozen=True, tag="fragment"):
    id: str | int
    data: str
    num: int
    total: int


class Advertise(Op, frozen=True, tag="advertise"):
    topic: str
    type: str
    id: Id = None
    latch: bool = False


class Unadvertise(Op, frozen=True, tag="unadvertise"):
    topic: str
    id: Id = None


class Publish(Op, frozen=True, tag="publish"):
    topic: str
    msg: dict[str, Any] = msgspec.field(default_factory=dict)
    id: Id = None
    latch: bool | None = None


class Subscribe(Op, frozen=True, tag="subscribe"):
    topic: str
    type: str | None = None
    id: Id = None
    throttle_rate: int | float = 0
    queue_length: int = 0
    fragment_size: int | None = None
    compression: str | None = None


class Unsubscribe(Op, frozen=True, tag="unsubscribe"):
    topic: str
    id: Id = None


class CallService(Op, frozen=True, tag="call_service"):
    service: str
    args: dict[str, Any] | list[Any] | None = None
    id: Id = None
    fragment_size: int | None = None
    compression: str | None = None
    timeout: int | float | None = None


class ServiceResponse(Op, frozen=True, tag="service_response"):
    service: str
    id: Id = None
    values: Any = None
    result: bool = True


class AdvertiseService(Op, frozen=True, tag="advertise_service"):
    service: str
    type: str
    id: Id = None


class UnadvertiseService(Op, frozen=True, tag="unadvertise_service"):
    service: str
    id: Id = None


class AdvertiseAction(Op, frozen=True, tag="advertise_action"):
    action: str
    type: str
    id: Id = None


class UnadvertiseAction(Op, frozen=True, tag="unadvertise_action"):
    action: str
    id: Id = None


class SendActionGoal(Op, frozen=True, tag="send_action_goal"):
    action: str
    action_type: str | None = None
    args: dict[str, Any] | list[Any] | None = None
    id: Id = None
    feedback: bool = False
    fragment_size: int | None = None
    compression: str | None = None


class CancelActionGoal(Op, frozen=True, tag="cancel_action_goal"):
    action: str
    id: str | int


class ActionFeedback(Op, frozen=True, tag="action_feedback"):
    action: str
    id: str | int
    values: Any = None


class ActionResult(Op, frozen=True, tag="action_result"):
    action: str
    id: str | int
    values: Any = None
    status: int = 4
    result: bool = True


OPS: tuple[type[Op], ...] = (
    Auth,
    SetLevel,
    Fragment,
    Advertise,
    Unadvertise,
    Publish,
    Subscribe,
    Unsubscribe,
    CallService,
    ServiceResponse,
    AdvertiseService,
    UnadvertiseService,
    AdvertiseAction,
    UnadvertiseAction,
    SendActionGoal,
    CancelActionGoal,
    ActionFeedback,
    ActionResult,
)
OP_NAMES: tuple[str, ...] = tuple(sorted(str(op.__struct_config__.tag) for op in OPS))

_decoder = msgspec.json.Decoder(
    Auth
    | SetLevel
    | Fragment
    | Advertise
    | Unadvertise
    | Publish
    | Subscribe
    | Unsubscribe
    | CallService
    | ServiceResponse
    | AdvertiseService
    | UnadvertiseService
    | AdvertiseAction
    | UnadvertiseAction
    | SendActionGoal
    | CancelActionGoal
    | ActionFeedback
    | ActionResult
)

_EXPECTED = re.compile(r"^Expected `([^`]+)`, got `([^`]+)`(?: - at `\$\.?(.*)`)?$")
_MISSING = re.compile(r"^Object missing required field `([^`]+)`(?: - at `\$\.?(.*)`)?$")
_INVALID = re.compile(r"^Invalid value (.+?)(?: - at `\$\.?(.*)`)?$")
_WORDS = {
    "str": "a string",
    "int": "an integer",
    "float": "a number",
    "bool": "a boolean",
    "object": "an object",
    "array": "an array",
    "null": "null",
}


def parse(text: str | bytes) -> Op:
    """Parse one frame; FrameError says what is wrong, naming the op and field."""
    try:
        return _decoder.decode(text)  # type: ignore[no-any-return]
    except msgspec.DecodeError as err:
        raise _explain(text, str(err)) from None


def peek_id(text: str | bytes) -> Id:
    """The ``id`` of a frame that failed to parse, if it has a usable one (for status)."""
    try:
        value = orjson.loads(text)
    except orjson.JSONDecodeError:
        return None
    if isinstance(value, dict):
        frame_id = value.get("id")
        if isinstance(frame_id, str | int) and not isinstance(frame_id, bool):
            return frame_id
    return None


def op_named(text: str | bytes) -> str | FrameError:
    """The ``op`` of a frame that did not parse, or why it has none: not JSON, not an
    object, no ``op``, or not a string (Foxglove's frames are JSON objects too)."""
    try:
        value = orjson.loads(text)
    except orjson.JSONDecodeError as err:
        return FrameError(f"the frame is not JSON ({err.msg} at character {err.pos})")
    if not isinstance(value, dict):
        return FrameError(f"a frame must be a JSON object, got {describe(value)}")
    op = value.get("op")
    if op is None:
        return FrameError("the frame has no 'op' field")
    if not isinstance(op, str):
        return FrameError(f"'op' must be a string, got {describe(op)}")
    return op


def _explain(text: str | bytes, message: str) -> FrameError:
    op = op_named(text)
    if isinstance(op, FrameError):
        return op
    if op not in OP_NAMES:
        return FrameError(f"unknown op {op!r}; the ops are {', '.join(OP_NAMES)}", op)
    if m := _EXPECTED.match(message):
        want, got, where = m.groups()
        return FrameError(f"{op}.{where} must be {_words(want)}, got {_words(got)}", op)
    if m := _MISSING.match(message):
        field, where = m.groups()
        return FrameError(f"{op}.{(where + '.') if where else ''}{field} is required", op)
    if m := _INVALID.match(message):
        return FrameError(f"{op}.{m.group(2) or 'op'} has an invalid value {m.group(1)}", op)
    return FrameError(f"{op}: {message}", op)


def _words(name: str) -> str:
    """``int | float | null`` -> ``a number``; ``int | str`` -> ``a string or an integer``."""
    parts = [p for p in name.split(" | ") if p != "null"] or ["null"]
    if "float" in parts and "int" in parts:
        parts.remove("int")
    words = sorted(_WORDS.get(p, p) for p in parts)
    return " or ".join(words[::-1] if words[-1].startswith("a string") else words)
