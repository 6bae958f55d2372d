"""The topic ops of the protocol core, driven with strings (no sockets)."""

from __future__ import annotations

import base64

import cbor2
import numpy as np
import orjson

from labd.bridge.render import png_decode
from labd.config import BridgeConfig

TWIST = "geometry_msgs/msg/Twist"


def test_publish_reaches_subscriber_with_defaults_filled(connect):
    """A published message arrives at another client with missing fields defaulted."""
    sub, pub = connect(), connect()
    sub.send({"op": "subscribe", "topic": "/cmd_vel", "type": TWIST, "id": "s1"})
    pub.send({"op": "advertise", "topic": "/cmd_vel", "type": "geometry_msgs/Twist"})
    pub.send({"op": "publish", "topic": "/cmd_vel", "msg": {"linear": {"x": 1}}})
    assert sub.frames() == [
        {
            "op": "publish",
            "topic": "/cmd_vel",
            "msg": {
                "linear": {"x": 1.0, "y": 0.0, "z": 0.0},
                "angular": {"x": 0.0, "y": 0.0, "z": 0.0},
            },
        }
    ]
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
    pub.send(
        {
            "op": "publish",
            "topic": "/img",
            "msg": {"data": [1, 2, 3], "header": {"stamp": {"sec": 1, "nanosec": 2}}},
        }
    )
    pub.send(
        {"op": "publish", "topic": "/img", "msg": {"data": base64.b64encode(b"\x04\x05").decode()}}
    )
    first, second = sub.frames()
    assert base64.b64decode(first["msg"]["data"]) == b"\x01\x02\x03"
    assert first["msg"]["header"]["stamp"] == {"sec": 1, "nanosec": 2}
    assert base64.b64decode(second["msg"]["data"]) == b"\x04\x05"


def test_png_compression_round_trips(connect):
    """compression=png sends a png op whose decoded text is the publish frame."""
    sub, pub = connect(), connect()
    sub.send(
        {"op": "subscribe", "topic": "/chatter", "type": "std_msgs/String", "compression": "png"}
    )
    pub.send({"op": "advertise", "topic": "/chatter", "type": "std_msgs/String"})
    pub.send({"op": "publish", "topic": "/chatter", "msg": {"data": "hello png"}})
    (frame,) = sub.frames()
    assert frame["op"] == "png"

    assert orjson.loads(png_decode(frame["data"])) == {
        "op": "publish",
        "topic": "/chatter",
        "msg": {"data": "hello png"},
    }


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


def publish_strings(pub, topic, values):
    pub.send({"op": "advertise", "topic": topic, "type": "std_msgs/String"})
    for value in values:
        pub.send({"op": "publish", "topic": topic, "msg": {"data": value}})


def test_throttle_sends_first_then_newest_at_interval_end(connect, timers):
    """With throttle_rate, the first message goes at once and the newest of the rest at the end."""
    sub, pub = connect(), connect()
    sub.send({"op": "subscribe", "topic": "/c", "type": "std_msgs/String", "throttle_rate": 100})
    publish_strings(pub, "/c", ["a", "b", "c"])
    assert [f["msg"]["data"] for f in sub.frames()] == ["a"]
    timers.advance(0.099)
    assert sub.frames() == []
    timers.advance(0.002)
    assert [f["msg"]["data"] for f in sub.frames()] == ["c"]
    timers.advance(1)
    assert sub.frames() == []


def test_throttle_with_queue_releases_one_per_interval(connect, timers):
    """With throttle_rate and queue_length N, the newest N wait and leave one per interval."""
    sub, pub = connect(), connect()
    sub.send(
        {
            "op": "subscribe",
            "topic": "/c",
            "type": "std_msgs/String",
            "throttle_rate": 50,
            "queue_length": 2,
        }
    )
    publish_strings(pub, "/c", ["a", "b", "c", "d"])
    assert [f["msg"]["data"] for f in sub.frames()] == ["a"]
    timers.advance(0.051)
    assert [f["msg"]["data"] for f in sub.frames()] == ["c"]
    timers.advance(0.051)
    assert [f["msg"]["data"] for f in sub.frames()] == ["d"]


def test_cbor_compression_sends_binary_with_typed_arrays(connect):
    """compression=cbor sends a binary CBOR frame; float arrays arrive as typed arrays."""
    sub, pub = connect(), connect()
    sub.send(
        {
            "op": "subscribe",
            "topic": "/js",
            "type": "sensor_msgs/msg/JointState",
            "compression": "cbor",
        }
    )
    pub.send({"op": "advertise", "topic": "/js", "type": "sensor_msgs/msg/JointState"})
    pub.send({"op": "publish", "topic": "/js", "msg": {"name": ["a"], "position": [1.5]}})
    frames = sub.session.next_frames()
    assert frames is not None and not frames[0].text
    decoded = cbor2.loads(frames[0].data)
    assert decoded["op"] == "publish" and decoded["msg"]["name"] == ["a"]
    position = decoded["msg"]["position"]
    assert np.frombuffer(position.value, "<f8").tolist() == [1.5] and position.tag == 86


def test_cbor_raw_sends_cdr(connect, registry):
    """compression=cbor-raw sends the CDR bytes, which deserialize to the message."""
    sub, pub = connect(), connect()
    sub.send(
        {"op": "subscribe", "topic": "/c", "type": "std_msgs/String", "compression": "cbor-raw"}
    )
    publish_strings(pub, "/c", ["raw"])
    (frame,) = sub.frames()
    msg = registry.typestore.deserialize_cdr(frame["msg"]["bytes"], "std_msgs/msg/String")
    assert msg.data == "raw" and set(frame["msg"]) == {"bytes", "secs", "nsecs"}


def test_latched_message_reaches_late_subscriber(connect):
    """A message published with latch is delivered to subscribers that join later."""
    pub = connect()
    pub.send({"op": "advertise", "topic": "/map", "type": "std_msgs/String", "latch": True})
    pub.send({"op": "publish", "topic": "/map", "msg": {"data": "the map"}})
    late = connect()
    late.send({"op": "subscribe", "topic": "/map", "type": "std_msgs/String"})
    assert [f["msg"]["data"] for f in late.frames()] == ["the map"]


def test_type_conflicts_are_refused(connect):
    """Advertising or subscribing with a type other than the topic's is an error."""
    a, b = connect(), connect()
    b.send({"op": "set_level", "level": "error"})
    a.send({"op": "advertise", "topic": "/t", "type": "std_msgs/String"})
    b.send({"op": "advertise", "topic": "/t", "type": "std_msgs/Int32"})
    b.send({"op": "subscribe", "topic": "/t", "type": "std_msgs/Int32"})
    statuses = b.frames()
    assert len(statuses) == 2
    assert all("has type std_msgs/msg/String, not std_msgs/msg/Int32" in s["msg"] for s in statuses)


def test_publish_auto_advertises_on_a_known_topic(connect, graph):
    """Publishing to a topic that exists, without advertising, advertises with its type."""
    sub, pub = connect(), connect()
    sub.send({"op": "subscribe", "topic": "/c", "type": "std_msgs/String"})
    pub.send({"op": "publish", "topic": "/c", "msg": {"data": "auto"}})
    assert [f["msg"]["data"] for f in sub.frames()] == ["auto"]
    assert pub.session.node.name in graph.publishers_of("/c")


def test_slow_client_does_not_slow_a_healthy_one(connect):
    """Messages dropped for a client that reads nothing are still all delivered to a reader."""
    stalled = connect(BridgeConfig(max_queue_bytes=10_000))
    healthy, pub = connect(), connect()
    for client in (stalled, healthy):
        client.send({"op": "subscribe", "topic": "/c", "type": "std_msgs/String"})
    pub.send({"op": "advertise", "topic": "/c", "type": "std_msgs/String"})
    received = 0
    for i in range(2000):
        pub.send({"op": "publish", "topic": "/c", "msg": {"data": "x" * 100 + str(i)}})
        received += len(healthy.frames())
    assert received == 2000
    assert stalled.session.outbox.pending_bytes <= 10_000
    assert stalled.session.outbox.dropped > 1800


def test_ux_events_are_rate_limited_per_client(connect, timers):
    """A client flooding /ux/events gets its burst through, then its rate, and is told
    once that the rest are dropped; another topic is not limited."""
    sub, page = connect(), connect()
    sub.send(
        {
            "op": "subscribe",
            "topic": "/ux/events",
            "type": "lab_msgs/msg/UxEvent",
            "queue_length": 500,
        }
    )
    page.send({"op": "set_level", "level": "warning"})
    page.send({"op": "advertise", "topic": "/ux/events", "type": "lab_msgs/msg/UxEvent"})
    for n in range(150):
        page.send({"op": "publish", "topic": "/ux/events", "msg": {"kind": "key", "key": str(n)}})
    assert len(sub.frames()) == 100  # the burst
    warnings = [f for f in page.frames() if f["op"] == "status"]
    assert len(warnings) == 1 and "at most 50 messages a second" in warnings[0]["msg"]
    timers.advance(0.1)  # five more tokens
    for n in range(10):
        page.send({"op": "publish", "topic": "/ux/events", "msg": {"kind": "key", "key": str(n)}})
    assert len(sub.frames()) == 5
    sub.send(
        {"op": "subscribe", "topic": "/chatter", "type": "std_msgs/msg/String", "queue_length": 500}
    )
    page.send({"op": "advertise", "topic": "/chatter", "type": "std_msgs/msg/String"})
    for _ in range(300):
        page.send({"op": "publish", "topic": "/chatter", "msg": {"data": "x"}})
    assert len(sub.frames()) == 300
