"""The topic ops of the protocol core, driven with strings (no sockets)."""

from __future__ import annotations

import base64

from labd.bridge.render import png_decode
from labd.config import BridgeConfig

TWIST = "geometry_msgs/msg/Twist"


def test_publish_reaches_subscriber_with_defaults_filled(connect):
    """A published message arrives at another client with missing fields defaulted."""
    sub, pub = connect(), connect()
    sub.send({"op": "subscribe", "topic": "/cmd_vel", "type": TWIST, "id": "s1"})
    pub.send({"op": "advertise", "topic": "/cmd_vel", "type": "geometry_msgs/Twist"})
    pub.send({"op": "publish", "topic": "/cmd_vel", "msg": {"linear": {"x": 1}}})
    assert sub.frames() == [{
        "op": "publish", "topic": "/cmd_vel",
        "msg": {"linear": {"x": 1.0, "y": 0.0, "z": 0.0}, "angular": {"x": 0.0, "y": 0.0, "z": 0.0}},
    }]
    assert pub.frames() == []


def test_topic_name_is_echoed_as_the_client_spelled_it(connect):
    """A relative subscription hears publishes on the absolute name, under its own spelling."""
    sub, pub = connect(), connect()
    sub.send({"op": "subscribe", "topic": "chatter", "type": "std_msgs/String"})
    pub.send({"op": "advertise", "topic": "/chatter", "type": "std_msgs/msg/String"})
    pub.send({"op": "publish", "topic": "/chatter", "msg": {"data": "hi"}})
    assert sub.frames() == [{"op": "publish", "topic": "chatter", "msg": {"data": "hi"}}]


def test_two_subscriptions_of_one_client_get_each_message_once(connect):
    """Clients dispatch by topic name, so a second subscription must not duplicate messages."""
    sub, pub = connect(), connect()
    for sub_id in ("a", "b"):
        sub.send({"op": "subscribe", "topic": "/chatter", "type": "std_msgs/String", "id": sub_id})
    pub.send({"op": "advertise", "topic": "/chatter", "type": "std_msgs/String"})
    pub.send({"op": "publish", "topic": "/chatter", "msg": {"data": "x"}})
    assert len(sub.frames()) == 1
    sub.send({"op": "unsubscribe", "topic": "/chatter", "id": "a"})
    pub.send({"op": "publish", "topic": "/chatter", "msg": {"data": "y"}})
    assert [f["msg"]["data"] for f in sub.frames()] == ["y"]
    sub.send({"op": "unsubscribe", "topic": "/chatter", "id": "b"})
    pub.send({"op": "publish", "topic": "/chatter", "msg": {"data": "z"}})
    assert sub.frames() == []


def test_wrong_field_type_is_a_status_naming_the_field(connect):
    """A publish with a wrong field type is refused with a status that names the field."""
    pub = connect()
    pub.send({"op": "set_level", "level": "error"})
    pub.send({"op": "advertise", "topic": "/cmd_vel", "type": TWIST})
    pub.send({"op": "publish", "id": "p1", "topic": "/cmd_vel", "msg": {"linear": {"x": "fast"}}})
    (status,) = pub.frames()
    assert status["op"] == "status" and status["level"] == "error" and status["id"] == "p1"
    assert "msg.linear.x must be a number" in status["msg"]


def test_no_status_without_set_level(connect):
    """Nothing is sent unsolicited: errors produce no frame until the client asks for status."""
    client = connect()
    client.send("this is not json")
    client.send({"op": "nope"})
    assert client.frames() == []


def test_uint8_arrays_travel_as_base64(connect):
    """uint8[] accepts base64 or a list of numbers and always goes out as base64."""
    sub, pub = connect(), connect()
    sub.send({"op": "subscribe", "topic": "/img", "type": "sensor_msgs/msg/Image"})
    pub.send({"op": "advertise", "topic": "/img", "type": "sensor_msgs/msg/Image"})
    pub.send({"op": "publish", "topic": "/img", "msg": {"data": [1, 2, 3], "header": {"stamp": {"sec": 1, "nanosec": 2}}}})
    pub.send({"op": "publish", "topic": "/img", "msg": {"data": base64.b64encode(b"\x04\x05").decode()}})
    first, second = sub.frames()
    assert base64.b64decode(first["msg"]["data"]) == b"\x01\x02\x03"
    assert first["msg"]["header"]["stamp"] == {"sec": 1, "nanosec": 2}
    assert base64.b64decode(second["msg"]["data"]) == b"\x04\x05"


def test_png_compression_round_trips(connect):
    """compression=png sends a png op whose decoded text is the publish frame."""
    sub, pub = connect(), connect()
    sub.send({"op": "subscribe", "topic": "/chatter", "type": "std_msgs/String", "compression": "png"})
    pub.send({"op": "advertise", "topic": "/chatter", "type": "std_msgs/String"})
    pub.send({"op": "publish", "topic": "/chatter", "msg": {"data": "hello png"}})
    (frame,) = sub.frames()
    assert frame["op"] == "png"
    import orjson
    assert orjson.loads(png_decode(frame["data"])) == {
        "op": "publish", "topic": "/chatter", "msg": {"data": "hello png"}}


def test_stalled_subscriber_queue_is_bounded(connect):
    """A client that reads nothing holds at most its queue's worth of messages."""
    sub, pub = connect(BridgeConfig(default_queue_length=5)), connect()
    sub.send({"op": "subscribe", "topic": "/chatter", "type": "std_msgs/String"})
    pub.send({"op": "advertise", "topic": "/chatter", "type": "std_msgs/String"})
    for i in range(1000):
        pub.send({"op": "publish", "topic": "/chatter", "msg": {"data": str(i)}})
    got = [f["msg"]["data"] for f in sub.frames()]
    assert got == [str(i) for i in range(995, 1000)]
    assert sub.session.outbox.dropped == 995
