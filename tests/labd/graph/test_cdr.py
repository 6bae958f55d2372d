"""The direct CDR encoder gives rosbags' bytes for every type and every field kind.

rosbags is the reference: the lab's records were written through it, and other tools
read them with it. Each test encodes seeded random values both ways and compares the
bytes; the values reach every layout case (empty sequences before 8-byte numbers,
strings of odd lengths before nested messages, fixed arrays of each primitive, empty
messages).
"""

from __future__ import annotations

import math
import random
import struct
from typing import Any

import numpy as np
import pytest
from rosbags.typesys import get_types_from_msg

from labd.graph.cdr import encoder
from labd.graph.codec import codec_for
from labd.graph.types import FLOATS, INTEGER_RANGES, Field, Kind, TypeRegistry

# Layouts the standard messages lack: fixed arrays of every primitive, of strings and
# of messages, bounded sequences, empty sequences before 8-byte numbers.
EXTRA = {
    "cdr_test/msg/Inner": "string s\nfloat64 x\nuint8 u",
    "cdr_test/msg/Nothing": "",
    "cdr_test/msg/Everything": """
bool flag
int8 small
string odd
float64 after_string
float32[3] f32s
float64[2] f64s
bool[3] bools
int8[3] i8s
uint8[5] raw
char[3] chars
int16[3] i16s
uint16[2] u16s
int32[3] i32s
uint32[2] u32s
int64[2] i64s
uint64[2] u64s
string[2] names
string<=5 short
float32[<=4] bounded
cdr_test/Inner[2] pair
cdr_test/Inner[] inners
cdr_test/Nothing nothing
cdr_test/Nothing[] nothings
int8[] i8seq
float64[] f64seq
uint8 last_byte
float64 aligned_after_sequence
bool[] boolseq
int16[] i16seq
int64 tail
""",
}


@pytest.fixture(scope="module")
def types() -> TypeRegistry:
    parts: dict[str, Any] = {}
    for name, text in EXTRA.items():
        parts.update(get_types_from_msg(text, name))
    return TypeRegistry.shared().extended(parts, (), ())


def random_value(types: TypeRegistry, name: str, rng: random.Random) -> dict[str, Any]:
    """A value of ``name`` in normal form, numbers and lengths drawn from ``rng``."""
    out: dict[str, Any] = {}
    for field in types.message(name).fields:
        if field.name == "structure_needs_at_least_one_member":
            continue
        if field.kind is Kind.SCALAR:
            out[field.name] = _item(types, field, rng)
            continue
        count = field.length if field.kind is Kind.ARRAY else rng.choice((0, 0, 1, 2, 3))
        if field.kind is Kind.SEQUENCE and field.length:
            count = min(count, field.length)
        items = [_item(types, field, rng) for _ in range(count)]
        out[field.name] = bytes(items) if field.is_binary else items
    return out


def _item(types: TypeRegistry, field: Field, rng: random.Random) -> Any:
    base = field.base
    if base is None:
        return random_value(types, field.message or "", rng)
    if base in FLOATS:
        value = rng.choice((0.0, -1.5, 1e-30, math.nan, math.inf, rng.uniform(-1e6, 1e6)))
        if base == "float32" and math.isfinite(value):
            value = struct.unpack("<f", struct.pack("<f", value))[0]
        return value
    if base in INTEGER_RANGES:
        low, high = INTEGER_RANGES[base]
        if base == "byte" and field.kind is Kind.SCALAR:
            high = 127  # rosbags packs a byte as signed (see test_a_byte_is_an_octet)
        return rng.choice((low, high, 0, rng.randint(low, high)))
    if base == "bool":
        return rng.random() < 0.5
    length = rng.randint(0, field.string_bound or 7)
    return "".join(rng.choice("ab€z") for _ in range(length))


def through_rosbags(types: TypeRegistry, name: str, value: dict[str, Any]) -> bytes:
    codec = codec_for(types, name)
    return bytes(types.typestore.serialize_cdr(codec.to_rosbags(value), name))


def test_every_lab_type_encodes_as_rosbags_does(types: TypeRegistry) -> None:
    """All 287 message types the lab knows (standard, its own, services' and actions'
    parts), several random values each."""
    rng = random.Random(21)
    names = [n for n in TypeRegistry.shared().typestore.fielddefs]
    assert len(names) > 250
    for name in names:
        codec = codec_for(types, name)
        for _ in range(4):
            value = random_value(types, name, rng)
            assert codec.to_cdr(value) == through_rosbags(types, name, value), name


def test_every_field_kind_encodes_as_rosbags_does(types: TypeRegistry) -> None:
    """Fixed arrays of each primitive, of strings and of messages, bounded and empty
    sequences, an empty message: many random values, each started at every offset
    that a string before it can leave."""
    rng = random.Random(5)
    codec = codec_for(types, "cdr_test/msg/Everything")
    for _ in range(300):
        value = random_value(types, "cdr_test/msg/Everything", rng)
        assert codec.to_cdr(value) == through_rosbags(types, "cdr_test/msg/Everything", value)


def test_decoded_values_encode_to_the_same_bytes(types: TypeRegistry) -> None:
    """A value decoded from CDR (numpy arrays where normal form has lists, as a replay's
    commands and the gym's observations come) encodes back to the bytes it came from."""
    rng = random.Random(8)
    name = "cdr_test/msg/Everything"
    codec = codec_for(types, name)
    for _ in range(50):
        data = through_rosbags(types, name, random_value(types, name, rng))
        decoded = codec.from_rosbags(types.typestore.deserialize_cdr(data, name))
        assert any(isinstance(v, np.ndarray) for v in decoded.values())
        assert codec.to_cdr(decoded) == data


def test_a_fixed_array_of_the_wrong_length_is_refused(types: TypeRegistry) -> None:
    """A fixed array is never silently cut or padded: each layout path refuses it."""
    value = random_value(types, "cdr_test/msg/Everything", random.Random(1))
    encode = encoder(types, "cdr_test/msg/Everything")
    for field, wrong in (("f64s", [1.0]), ("f32s", [1.0] * 4), ("raw", b"\0" * 4)):
        with pytest.raises((ValueError, struct.error)):
            encode({**value, field: wrong}, bytearray())
    with pytest.raises((ValueError, struct.error)):
        encode({**value, "names": ["one"]}, bytearray())


def test_a_byte_is_an_octet(types: TypeRegistry) -> None:
    """A ``byte`` is an octet, 0 to 255, as the lab's JSON takes it; rosbags packs it as
    a signed number, so a byte above 127 could not be recorded before: now it is."""
    codec = codec_for(types, "diagnostic_msgs/msg/DiagnosticStatus")
    value = {**codec.default(), "level": 200}
    assert codec.to_cdr(value)[4] == 200
    with pytest.raises(struct.error):
        through_rosbags(types, "diagnostic_msgs/msg/DiagnosticStatus", value)


def test_encoders_are_compiled_once_per_type(types: TypeRegistry) -> None:
    """The lab's types are compiled once, in the lab's registry, for every trial."""
    lab = TypeRegistry.shared()
    first = encoder(lab, "nav_msgs/msg/Odometry")
    assert encoder(lab, "nav_msgs/msg/Odometry") is first
    assert codec_for(types, "nav_msgs/msg/Odometry") is codec_for(lab, "nav_msgs/msg/Odometry")
