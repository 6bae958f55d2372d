"""Conversion between JSON and typed messages: validation, defaults, renderings."""

from __future__ import annotations

import base64
import math

import numpy as np
import orjson
import pytest

from labd.errors import MessageError, UnknownTypeError
from labd.graph.codec import codec_for, dumps
from labd.graph.types import TypeRegistry


def now() -> tuple[int, int]:
    return (7, 8)


def normalize(registry: TypeRegistry, type_name: str, value):
    return codec_for(registry, type_name).normalize(value, now)


def error(registry: TypeRegistry, type_name: str, value) -> str:
    with pytest.raises(MessageError) as info:
        normalize(registry, type_name, value)
    return str(info.value)


def test_missing_fields_take_defaults(registry):
    """An empty object is a valid message whose every field has its zero value."""
    assert normalize(registry, "sensor_msgs/msg/JointState", {}) == {
        "header": {"stamp": {"sec": 0, "nanosec": 0}, "frame_id": ""},
        "name": [],
        "position": [],
        "velocity": [],
        "effort": [],
    }


def test_header_is_stamped_only_when_given_without_stamp(registry):
    """A header present without a stamp gets the graph's time; an absent header stays zero."""
    stamped = normalize(registry, "std_msgs/msg/Header", {"frame_id": "map"})
    assert stamped == {"stamp": {"sec": 7, "nanosec": 8}, "frame_id": "map"}
    absent = normalize(registry, "geometry_msgs/msg/PoseStamped", {})
    assert absent["header"]["stamp"] == {"sec": 0, "nanosec": 0}


def test_times_accept_ros1_names_and_now(registry):
    """Times take sec/nanosec, the ROS 1 secs/nsecs, or "now", and always leave as sec/nanosec."""
    t = "builtin_interfaces/msg/Time"
    assert normalize(registry, t, {"secs": 3, "nsecs": 4}) == {"sec": 3, "nanosec": 4}
    assert normalize(registry, t, "now") == {"sec": 7, "nanosec": 8}
    assert "nanosec must be between 0" in error(registry, t, {"sec": 1, "nanosec": -1})
    assert "is not a field" in error(registry, t, {"sec": 1, "minutes": 2})


def test_wrong_types_name_the_field(registry):
    """Each kind of mismatch is refused with the path to the field and what was expected."""
    twist = "geometry_msgs/msg/Twist"
    assert error(registry, twist, {"linear": {"x": "1"}}) == (
        "linear.x must be a number (float64), got a string"
    )
    assert error(registry, twist, {"linear": {"x": True}}).startswith("linear.x must be a number")
    assert error(registry, twist, {"linear": [1, 2, 3]}).startswith("linear must be an object")
    assert error(registry, twist, {"spin": 1}) == "spin is not a field of geometry_msgs/msg/Twist"
    path = "geometry_msgs/msg/PoseArray"
    assert error(registry, path, {"poses": [{}, {"position": {"x": [1]}}]}) == (
        "poses[1].position.x must be a number (float64), got an array"
    )


def test_nan_and_infinity_travel_as_null(registry):
    """Non-finite floats leave as null (JSON has no NaN), and null comes back in as NaN."""
    scan = normalize(registry, "sensor_msgs/msg/LaserScan", {"ranges": [1.0, None]})
    assert math.isnan(scan["ranges"][1])
    rendered = orjson.loads(dumps({"ranges": [float("inf"), float("nan"), 2.0]}))
    assert rendered == {"ranges": [None, None, 2.0]}
    assert "must be an integer" in error(registry, "std_msgs/msg/Int32", {"data": None})


def test_integer_ranges_are_enforced(registry):
    """Integers must fit their type; integral floats are accepted, fractions are not."""
    assert normalize(registry, "std_msgs/msg/UInt8", {"data": 255.0}) == {"data": 255}
    assert "between 0 and 255" in error(registry, "std_msgs/msg/UInt8", {"data": 256})
    assert "must be an integer" in error(registry, "std_msgs/msg/Int32", {"data": 1.5})
    assert "between -128 and 127" in error(registry, "std_msgs/msg/Int8", {"data": -129})


def test_fixed_arrays_must_have_their_length(registry):
    """A float64[9] takes exactly nine numbers."""
    info = "sensor_msgs/msg/CameraInfo"
    assert error(registry, info, {"k": [1, 2]}) == "k must hold exactly 9 items, got 2"
    assert normalize(registry, info, {"k": list(range(9))})["k"] == [float(i) for i in range(9)]


def test_binary_fields_take_base64_or_numbers(registry):
    """uint8[] is bytes inside, from base64 text or a list of small integers."""
    img = "sensor_msgs/msg/Image"
    assert normalize(registry, img, {"data": "AQID"})["data"] == b"\x01\x02\x03"
    assert normalize(registry, img, {"data": [1, 2, 3]})["data"] == b"\x01\x02\x03"
    assert "base64" in error(registry, img, {"data": "@@@"})
    assert "0..255" in error(registry, img, {"data": [1, 300]})
    rendered = orjson.loads(dumps(normalize(registry, img, {"data": [1, 2, 3]})))
    assert rendered["data"] == base64.b64encode(b"\x01\x02\x03").decode()


def test_unknown_type_is_refused(registry):
    """A type name that no definition backs is an UnknownTypeError naming it."""
    with pytest.raises(UnknownTypeError, match="nosuch_msgs/Thing"):
        codec_for(registry, "nosuch_msgs/Thing")
    with pytest.raises(UnknownTypeError):
        registry.service("std_msgs/String")


def test_empty_service_parts_hide_the_placeholder(registry):
    """Empty messages (std_srvs/Empty) are {} in JSON, though CDR needs a placeholder byte."""
    codec = codec_for(registry, "std_srvs/srv/Empty_Request")
    assert codec.normalize({}, now) == {}
    obj = codec.to_rosbags({})
    assert registry.typestore.serialize_cdr(obj, "std_srvs/srv/Empty_Request").tobytes()


def test_cdr_round_trip_preserves_the_value(registry):
    """Normal form -> rosbags -> CDR -> rosbags -> normal form is the identity."""
    codec = codec_for(registry, "sensor_msgs/msg/JointState")
    value = codec.normalize(
        {
            "header": {"stamp": {"sec": 1, "nanosec": 2}, "frame_id": "base"},
            "name": ["a", "b"],
            "position": [0.5, -1.25],
            "velocity": [1, 2],
            "effort": [],
        },
        now,
    )
    raw = registry.typestore.serialize_cdr(codec.to_rosbags(value), codec.type.name)
    back = codec.from_rosbags(registry.typestore.deserialize_cdr(raw, codec.type.name))
    assert orjson.loads(dumps(back)) == orjson.loads(dumps(value))
    assert isinstance(back["position"], np.ndarray)


def test_cbor_uses_typed_arrays(registry):
    """CBOR renderings carry numeric arrays as RFC 8746 little-endian typed arrays."""
    codec = codec_for(registry, "sensor_msgs/msg/JointState")
    value = codec.normalize({"position": [1.0, 2.0]}, now)
    tagged = codec.to_cbor(value)["position"]
    assert tagged.tag == 86
    assert np.frombuffer(tagged.value, "<f8").tolist() == [1.0, 2.0]
