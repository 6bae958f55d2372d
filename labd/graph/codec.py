"""Conversion between JSON values and typed messages, with validation.

A message travels through the graph in its *normal form*: a dict holding exactly the
fields of its type, in definition order, each value of the right Python type:

- integers and floats as ``int`` and ``float``, strings as ``str``;
- ``uint8[]`` and ``char[]`` (fixed or not) as ``bytes``;
- other numeric arrays as lists (or numpy arrays, when they came from CDR);
- times and durations as ``{"sec": int, "nanosec": int}``;
- nested messages as dicts in normal form.

``Codec.normalize`` turns JSON from a client into normal form: missing fields take
their defaults, ``uint8[]`` may be base64 or a list of numbers, times may use the
ROS 1 names (``secs``/``nsecs``) or the string ``"now"``, a ``std_msgs/Header``
without a stamp is stamped with the graph's time, and anything else that does not
fit raises ``MessageError`` naming the field. ``to_json`` and ``to_cbor`` render
normal form for the wire; ``to_cdr`` encodes it for recording and ``cbor-raw``
(``labd.graph.cdr``); ``to_rosbags``/``from_rosbags`` cross to the rosbags classes,
used to decode CDR.

Converters are compiled once per type into closures: the success path builds no
strings and never looks at a type description.
"""

from __future__ import annotations

import base64
import binascii
from collections.abc import Callable
from typing import Any

import numpy as np
import orjson
from cbor2 import CBORTag

from labd.errors import MessageError
from labd.graph.cdr import to_cdr_function
from labd.graph.types import (
    BINARY,
    FLOATS,
    INTEGER_RANGES,
    NUMPY_DTYPES,
    PLACEHOLDER,
    Field,
    Kind,
    MessageType,
    TypeRegistry,
)

Now = Callable[[], tuple[int, int]]
Normalizer = Callable[[Any, Now], Any]
Converter = Callable[[Any], Any]

NAN = float("nan")
TIME_TYPES = frozenset({"builtin_interfaces/msg/Time", "builtin_interfaces/msg/Duration"})
HEADER = "std_msgs/msg/Header"
# RFC 8746 typed-array tags, little-endian, as rosbridge's cbor compression uses.
_CBOR_TAGS = {
    "uint16": 69,
    "uint32": 70,
    "uint64": 71,
    "int8": 72,
    "int16": 77,
    "int32": 78,
    "int64": 79,
    "float32": 85,
    "float64": 86,
}


def json_default(value: Any) -> Any:
    """orjson fallback: bytes become base64 text, as rosbridge sends ``uint8[]``."""
    if isinstance(value, bytes | bytearray | memoryview):
        return base64.b64encode(value).decode("ascii")
    raise TypeError(f"cannot render {type(value).__name__} as JSON")


def dumps(value: Any) -> bytes:
    """JSON bytes of a normal-form value (or any frame holding one)."""
    return orjson.dumps(value, default=json_default, option=orjson.OPT_SERIALIZE_NUMPY)


class Codec:
    """Compiled converters for one message type."""

    def __init__(self, registry: TypeRegistry, mtype: MessageType) -> None:
        self.type = mtype
        self.registry = registry
        self.type_store = registry.typestore
        self._to_cdr: Converter | None = None
        self.has_binary = False  # any uint8[] inside, at any depth (for memory estimates)
        # Filled in by ``codec_for`` once every nested codec exists (types may nest deeply).
        self.normalize: Normalizer
        self.default: Callable[[], dict[str, Any]]
        self.to_rosbags: Converter
        self.from_rosbags: Converter
        self.to_cbor: Converter

    def to_cdr(self, value: dict[str, Any]) -> bytes:
        """The CDR (little-endian, with its header) of a value in normal form."""
        encode = self._to_cdr
        if encode is None:
            encode = self._to_cdr = to_cdr_function(self.registry, self.type.name)
            if encode is None:  # a type the direct encoder cannot lay out
                encode = self._to_cdr = self._rosbags_cdr
        return encode(value)

    def _rosbags_cdr(self, value: dict[str, Any]) -> bytes:
        return bytes(self.type_store.serialize_cdr(self.to_rosbags(value), self.type.name))


def codec_for(registry: TypeRegistry, name: str) -> Codec:
    """The codec of a message type, compiled on first use and cached in the registry."""
    mtype = registry.message(name)
    owner = registry.owner(mtype.name)
    if owner is not registry:  # a trial's own registry shares the lab's codecs
        return codec_for(owner, mtype.name)
    cache = registry.codec_cache()
    codec = cache.get(mtype.name)
    if codec is None:
        codec = Codec(registry, mtype)
        cache[mtype.name] = codec
        _compile(registry, codec)
    assert isinstance(codec, Codec)
    return codec


def _compile(registry: TypeRegistry, codec: Codec) -> None:
    mtype = codec.type
    fields = [f for f in mtype.fields if f.name != PLACEHOLDER]
    codec.has_binary = any(
        f.is_binary or (f.message is not None and codec_for(registry, f.message).has_binary)
        for f in fields
    )
    has_placeholder = len(fields) != len(mtype.fields)
    cls = registry.typestore.types[mtype.name]

    if mtype.name in TIME_TYPES:
        codec.normalize = _normalize_time(mtype.name)
        codec.default = lambda: {"sec": 0, "nanosec": 0}
        codec.to_rosbags = lambda v: cls(sec=v["sec"], nanosec=v["nanosec"])
        codec.from_rosbags = lambda o: {"sec": int(o.sec), "nanosec": int(o.nanosec)}
        codec.to_cbor = _identity
        return

    normalizers = [
        (f.name, _field_normalizer(registry, f), _field_default(registry, f)) for f in fields
    ]
    known = frozenset(f.name for f in fields) | ({PLACEHOLDER} if has_placeholder else set())
    type_name = mtype.name
    is_header = type_name == HEADER

    def normalize(value: Any, now: Now) -> dict[str, Any]:
        if type(value) is not dict:
            raise MessageError(f"must be an object ({type_name}), got {describe(value)}")
        out: dict[str, Any] = {}
        seen = 0
        for name, norm, default in normalizers:
            if name in value:
                seen += 1
                try:
                    out[name] = norm(value[name], now)
                except MessageError as err:
                    raise err.prefixed(name) from None
            else:
                out[name] = default()
        if seen != len(value):
            extra = sorted(str(k) for k in value if k not in known)
            if extra:
                raise MessageError(f"is not a field of {type_name}", [extra[0]])
        if is_header and "stamp" not in value:
            sec, nanosec = now()
            out["stamp"] = {"sec": sec, "nanosec": nanosec}
        return out

    defaults = [(name, default) for name, _, default in normalizers]

    def default() -> dict[str, Any]:
        return {name: make() for name, make in defaults}

    codec.normalize = normalize
    codec.default = default
    _compile_conversions(registry, codec, fields, has_placeholder)


def _compile_conversions(
    registry: TypeRegistry, codec: Codec, fields: list[Field], has_placeholder: bool
) -> None:
    """The converters to and from rosbags classes, and to CBOR values."""
    cls = registry.typestore.types[codec.type.name]
    to_rb = [(f.name, _field_to_rosbags(registry, f)) for f in fields]

    def to_rosbags(value: dict[str, Any]) -> Any:
        return cls(
            **{name: conv(value[name]) for name, conv in to_rb},
            **({PLACEHOLDER: 0} if has_placeholder else {}),
        )

    from_rb = [(f.name, _field_from_rosbags(registry, f)) for f in fields]

    def from_rosbags(obj: Any) -> dict[str, Any]:
        return {name: conv(getattr(obj, name)) for name, conv in from_rb}

    to_cb = [(f.name, _field_to_cbor(registry, f)) for f in fields]
    if all(conv is _identity for _, conv in to_cb):
        to_cbor: Converter = _identity
    else:

        def to_cbor(value: dict[str, Any]) -> dict[str, Any]:
            return {name: conv(value[name]) for name, conv in to_cb}

    codec.to_rosbags = to_rosbags
    codec.from_rosbags = from_rosbags
    codec.to_cbor = to_cbor


# -- normalizing JSON -----------------------------------------------------------------


def describe(value: Any) -> str:
    """A JSON value's kind in words, for error messages: 'a string', 'null', ..."""
    if value is None:
        return "null"
    return {
        bool: "a boolean",
        int: "an integer",
        float: "a number",
        str: "a string",
        list: "an array",
        dict: "an object",
    }.get(type(value), type(value).__name__)


def _scalar_normalizer(base: str, string_bound: int) -> Normalizer:
    if base in FLOATS:

        def norm_float(v: Any, now: Now) -> float:
            t = type(v)
            if t is float:
                return v  # type: ignore[no-any-return]
            if t is int:
                return float(v)
            if v is None:
                return NAN  # what NaN and infinities become in JSON, accepted back
            raise MessageError(f"must be a number ({base}), got {describe(v)}")

        return norm_float
    if base in INTEGER_RANGES:
        low, high = INTEGER_RANGES[base]

        def norm_int(v: Any, now: Now) -> int:
            t = type(v)
            if t is float and v.is_integer():
                v = int(v)
            elif t is not int:
                raise MessageError(f"must be an integer ({base}), got {describe(v)}")
            if not low <= v <= high:
                raise MessageError(f"must be between {low} and {high} ({base}), got {v}")
            return v  # type: ignore[no-any-return]

        return norm_int
    if base == "bool":

        def norm_bool(v: Any, now: Now) -> bool:
            if type(v) is bool:
                return v
            raise MessageError(f"must be a boolean, got {describe(v)}")

        return norm_bool
    if base == "string":

        def norm_str(v: Any, now: Now) -> str:
            if type(v) is not str:
                raise MessageError(f"must be a string, got {describe(v)}")
            if string_bound and len(v) > string_bound:
                raise MessageError(f"must be at most {string_bound} characters long")
            return v

        return norm_str
    raise MessageError(f"fields of type {base} are not supported")


def _normalize_binary(field: Field) -> Normalizer:
    fixed = field.length if field.kind is Kind.ARRAY else 0
    bound = field.length if field.kind is Kind.SEQUENCE else 0

    def norm(v: Any, now: Now) -> bytes:
        t = type(v)
        if t is str:
            try:
                data = base64.b64decode(v, validate=True)
            except (binascii.Error, ValueError):
                raise MessageError("must be base64 text or an array of bytes") from None
        elif t is bytes:
            data = v
        elif t is list:
            try:
                data = bytes(v)
            except (TypeError, ValueError):
                raise MessageError("must be base64 text or an array of integers 0..255") from None
        else:
            raise MessageError(f"must be base64 text or an array of bytes, got {describe(v)}")
        if fixed and len(data) != fixed:
            raise MessageError(f"must hold exactly {fixed} bytes, got {len(data)}")
        if bound and len(data) > bound:
            raise MessageError(f"must hold at most {bound} bytes, got {len(data)}")
        return data

    return norm


def _field_normalizer(registry: TypeRegistry, field: Field) -> Normalizer:
    if field.is_binary:
        return _normalize_binary(field)
    if field.base is not None:
        inner = _scalar_normalizer(field.base, field.string_bound)
        if field.kind is Kind.SCALAR:
            return inner
    else:
        nested = codec_for(registry, field.message or "")
        if field.kind is Kind.SCALAR:
            return nested.normalize
        inner = nested.normalize
    fixed = field.length if field.kind is Kind.ARRAY else 0
    bound = field.length if field.kind is Kind.SEQUENCE else 0
    fast = _fast_numbers(field.base)

    def norm_array(v: Any, now: Now) -> list[Any]:
        if type(v) is not list:
            if isinstance(v, np.ndarray):
                v = v.tolist()
            else:
                raise MessageError(f"must be an array, got {describe(v)}")
        if fixed and len(v) != fixed:
            raise MessageError(f"must hold exactly {fixed} items, got {len(v)}")
        if bound and len(v) > bound:
            raise MessageError(f"must hold at most {bound} items, got {len(v)}")
        if fast is not None:
            done = fast(v)
            if done is not None:
                return done
        out = []
        for i, item in enumerate(v):
            try:
                out.append(inner(item, now))
            except MessageError as err:
                raise err.prefixed(i) from None
        return out

    return norm_array


def _fast_numbers(base: str | None) -> Callable[[list[Any]], list[Any] | None] | None:
    """A check of a whole list of numbers done in C (map, set, min, max), or None.

    It answers None when the list needs the item-by-item path (which also names the
    bad item).
    """
    if base in FLOATS:

        def floats(v: list[Any]) -> list[Any] | None:
            kinds = set(map(type, v))
            if kinds <= {float}:
                return list(v)  # a copy: normal form never shares the caller's list
            if kinds <= {float, int}:
                return list(map(float, v))
            return None

        return floats
    if base in INTEGER_RANGES:
        low, high = INTEGER_RANGES[base]

        def ints(v: list[Any]) -> list[Any] | None:
            if set(map(type, v)) <= {int} and (not v or (low <= min(v) and max(v) <= high)):
                return list(v)
            return None

        return ints
    return None


def _normalize_time(type_name: str) -> Normalizer:
    allow_now = type_name.endswith("/Time")

    def norm(v: Any, now: Now) -> dict[str, int]:
        if v == "now" and allow_now:
            sec_now, nanosec_now = now()
            return {"sec": sec_now, "nanosec": nanosec_now}
        if type(v) is not dict:
            raise MessageError(f"must be an object with sec and nanosec, got {describe(v)}")
        sec: Any = v.get("sec", v.get("secs", 0))
        nanosec: Any = v.get("nanosec", v.get("nsecs", 0))
        extra = set(v) - {"sec", "secs", "nanosec", "nsecs"}
        if extra:
            raise MessageError(f"is not a field of {type_name}", [sorted(extra)[0]])
        return {
            "sec": _time_part("sec", sec, -(2**31), 2**31 - 1),
            "nanosec": _time_part("nanosec", nanosec, 0, 2**32 - 1),
        }

    return norm


def _time_part(key: str, value: Any, low: int, high: int) -> int:
    if type(value) is float and value.is_integer():
        value = int(value)
    if type(value) is not int:
        raise MessageError(f"must be an integer, got {describe(value)}", [key])
    if not low <= value <= high:
        raise MessageError(f"must be between {low} and {high}, got {value}", [key])
    return value


# -- defaults ---------------------------------------------------------------------------


def _scalar_default(base: str) -> Any:
    if base in FLOATS:
        return 0.0
    if base == "bool":
        return False
    if base == "string":
        return ""
    return 0


def _field_default(registry: TypeRegistry, field: Field) -> Callable[[], Any]:
    if field.is_binary:
        zeros = bytes(field.length if field.kind is Kind.ARRAY else 0)
        return lambda: zeros
    if field.base is not None:
        value = _scalar_default(field.base)
        if field.kind is Kind.SCALAR:
            return lambda: value
        if field.kind is Kind.ARRAY:
            n = field.length
            return lambda: [value] * n
        return list
    nested = codec_for(registry, field.message or "")
    if field.kind is Kind.SCALAR:
        return nested.default
    if field.kind is Kind.ARRAY:
        n = field.length
        return lambda: [nested.default() for _ in range(n)]
    return list


# -- rosbags classes (for CDR) ----------------------------------------------------------


def _identity(v: Any) -> Any:
    return v


def _field_to_rosbags(registry: TypeRegistry, field: Field) -> Converter:
    if field.kind is Kind.SCALAR:
        if field.base is not None:
            return _identity
        nested = codec_for(registry, field.message or "")
        return nested.to_rosbags
    if field.base is not None:
        if field.base == "string":
            return list
        dtype = np.dtype(NUMPY_DTYPES[field.base])
        if field.is_binary:
            return lambda v: np.frombuffer(v, dtype=dtype)
        return lambda v: np.asarray(v, dtype=dtype)
    nested = codec_for(registry, field.message or "")
    conv = nested.to_rosbags
    return lambda v: [conv(item) for item in v]


def _field_from_rosbags(registry: TypeRegistry, field: Field) -> Converter:
    if field.kind is Kind.SCALAR:
        if field.base is not None:
            if field.base in FLOATS:
                return float
            if field.base in INTEGER_RANGES:
                return int
            return _identity
        nested = codec_for(registry, field.message or "")
        return nested.from_rosbags
    if field.base is not None:
        if field.is_binary:
            return lambda v: np.ascontiguousarray(v, dtype=np.uint8).tobytes()
        if field.base == "string":
            return list
        if field.base == "bool":
            return lambda v: [bool(x) for x in v]
        return np.asarray
    nested = codec_for(registry, field.message or "")
    conv = nested.from_rosbags
    return lambda v: [conv(item) for item in v]


# -- CBOR -------------------------------------------------------------------------------


def _field_to_cbor(registry: TypeRegistry, field: Field) -> Converter:
    if field.is_binary:
        return _identity  # bytes: a CBOR byte string, as rosbridge sends uint8[]
    if field.base is not None:
        tag = _CBOR_TAGS.get(field.base)
        if field.kind is Kind.SCALAR or tag is None:
            return _identity
        dtype = np.dtype(NUMPY_DTYPES[field.base])
        return lambda v: CBORTag(tag, np.asarray(v, dtype=dtype).tobytes())
    nested = codec_for(registry, field.message or "")
    if nested.to_cbor is _identity:
        return _identity
    if field.kind is Kind.SCALAR:
        return nested.to_cbor
    conv = nested.to_cbor
    return lambda v: [conv(item) for item in v]


__all__ = ["BINARY", "Codec", "codec_for", "dumps", "json_default"]
