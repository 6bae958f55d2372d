"""A Foxglove session's logic, driven with frames on a manual clock (no I/O): what it
advertises and when, messages and time, client publishing, services, parameters, the
connection graph, keys, and a client that does not read."""

from __future__ import annotations

import struct
from collections.abc import Callable, Iterator
from typing import Any

import orjson
import pytest

from labd.bridge.foxglove import wire
from labd.bridge.foxglove.session import FoxgloveSession, ServerInfo
from labd.config import BridgeConfig
from labd.errors import FrameError
from labd.graph.graph import Graph
from tests.fakes import ManualTimers, RecordingTransport

TWIST = "geometry_msgs/msg/Twist"
IMAGE = "sensor_msgs/msg/CompressedImage"


class Fox:
    """One Foxglove client, as a test sees it: frames in, frames out, decoded."""

    def __init__(self, session: FoxgloveSession, transport: RecordingTransport) -> None:
        self.session = session
        self.transport = transport

    def send(self, frame: dict[str, Any] | bytes) -> None:
        self.session.receive(frame if isinstance(frame, bytes) else orjson.dumps(frame).decode())

    def frames(self) -> list[Any]:
        """Everything queued: JSON frames as dicts, binary ones as (opcode, fields...)."""
        out: list[Any] = []
        while (batch := self.session.next_frames()) is not None:
            for frame in batch:
                out.append(orjson.loads(frame.data) if frame.text else binary(frame.data))
        return out

    def ops(self, name: str) -> list[dict[str, Any]]:
        return [f for f in self.frames() if isinstance(f, dict) and f["op"] == name]

    def channel(self, topic: str, frames: list[Any]) -> int:
        for frame in frames:
            if isinstance(frame, dict) and frame["op"] == "advertise":
                for channel in frame["channels"]:
                    if channel["topic"] == topic:
                        return int(channel["id"])
        raise AssertionError(f"{topic} was not advertised in {frames}")


def binary(data: bytes) -> tuple[Any, ...]:
    if data[0] == wire.MESSAGE_DATA:
        sub, ns = struct.unpack_from("<IQ", data, 1)
        return ("message", sub, ns, data[13:])
    if data[0] == wire.TIME:
        return ("time", struct.unpack_from("<Q", data, 1)[0])
    if data[0] == wire.SERVICE_CALL_RESPONSE:
        service, call, length = struct.unpack_from("<III", data, 1)
        return ("response", service, call, data[13 : 13 + length].decode(), data[13 + length :])
    raise AssertionError(f"opcode {data[0]}")


@pytest.fixture
def fox(graph: Graph, timers: ManualTimers) -> Iterator[Callable[..., Fox]]:
    made: list[FoxgloveSession] = []
    ids = iter(range(1, 1000))

    def make(config: BridgeConfig | None = None, **kwargs: Any) -> Fox:
        transport = RecordingTransport()
        session = FoxgloveSession(
            graph,
            config or BridgeConfig(),
            timers,
            transport,
            client_id=next(ids),
            info=ServerInfo("labd test", "boot-test"),
            **kwargs,
        )
        made.append(session)
        return Fox(session, transport)

    yield make
    for session in made:
        session.close()


# -- what is advertised, and when -------------------------------------------------------------


def test_server_info_comes_first_then_the_channels_and_services(graph, fox):
    """serverInfo is the first frame; then every topic that has a publisher is a CDR
    channel with its ROS 2 definition, and every service is advertised with its
    request and response definitions. A topic nobody publishes (only subscribed) and
    protected names are not."""
    robot = graph.create_node("/robot")
    robot.advertise("/odom", "nav_msgs/msg/Odometry")
    robot.advertise("/protected/secret", "std_msgs/msg/String")
    robot.subscribe("/cmd_vel", TWIST, lambda m: None)
    frames = fox().frames()
    info = frames[0]
    assert info["op"] == "serverInfo"
    assert info["capabilities"] == [
        "clientPublish",
        "services",
        "parameters",
        "time",
        "connectionGraph",
    ]
    assert info["sessionId"] == "boot-test"
    [advertise] = [f for f in frames if f["op"] == "advertise"]
    topics = {c["topic"]: c for c in advertise["channels"]}
    assert set(topics) == {"/odom", "/rosout"}
    odom = topics["/odom"]
    assert odom["encoding"] == "cdr" and odom["schemaEncoding"] == "ros2msg"
    assert odom["schema"] == graph.types.definition_text("nav_msgs/msg/Odometry")
    [services] = [f for f in frames if f["op"] == "advertiseServices"]
    names = {s["name"]: s for s in services["services"]}
    assert "/rosapi/topics" in names and not any(n.startswith("/protected") for n in names)
    topics_srv = names["/rosapi/topics"]
    assert topics_srv["type"] == "rosapi_msgs/srv/Topics"
    assert topics_srv["response"]["schemaName"] == "rosapi_msgs/srv/Topics_Response"
    assert topics_srv["responseSchema"] == topics_srv["response"]["schema"]


def test_channels_follow_the_graph(graph, fox, timers):
    """A topic that gains a publisher is advertised once the loop turns; one that loses
    its last is unadvertised, and the client's subscription to it ends."""
    client = fox()
    client.frames()
    node = graph.create_node("/talker")
    pub = node.advertise("/chatter", "std_msgs/msg/String")
    node.advertise("/other", "std_msgs/msg/String")  # two changes, one advertise
    assert client.frames() == []  # not before the loop turns
    timers.advance(0)
    frames = client.frames()
    assert [f["op"] for f in frames] == ["advertise"]
    assert [c["topic"] for c in frames[0]["channels"]] == ["/chatter", "/other"]
    chatter = client.channel("/chatter", frames)
    client.send({"op": "subscribe", "subscriptions": [{"id": 3, "channelId": chatter}]})
    assert graph.subscribers_of("/chatter") == [client.session.node.name]
    pub.close()
    timers.advance(0)
    assert client.ops("unadvertise") == [{"op": "unadvertise", "channelIds": [chatter]}]
    assert "/chatter" not in graph.topics  # the session's subscription went with it


def test_nothing_but_server_info_before_the_key_is_granted(graph, fox, timers):
    """A robot that needs a key: serverInfo at once, the channels only once the key
    (from the URL, or an auth frame) is granted; frames sent meanwhile wait."""
    graph.create_node("/robot").advertise("/odom", "nav_msgs/msg/Odometry")
    client = fox(auth_required=True, url_key="k")
    assert client.transport.keys == ["k"]
    assert [f["op"] for f in client.frames()] == ["serverInfo"]
    client.send({"op": "getParameters", "parameterNames": [], "id": "early"})
    client.session.grant(30, user="ann")
    ops = [f["op"] for f in client.frames()]
    assert ops == ["parameterValues", "advertise", "advertiseServices"]
    assert client.session.node.user == "ann"


def test_a_first_frame_that_is_no_key_closes_saying_why_in_a_status(fox):
    client = fox(auth_required=True)
    client.frames()
    client.send({"op": "subscribe", "subscriptions": []})
    assert client.transport.closed is not None and client.transport.closed[0] == 1008
    [status] = client.ops("status")
    assert status["level"] == 2 and '"op": "auth"' in status["message"]


def test_an_auth_frame_presents_the_key(fox):
    client = fox(auth_required=True)
    client.send({"op": "auth", "key": "from-frame"})
    assert client.transport.keys == ["from-frame"]
    client.session.refuse("the key is not known")
    assert client.transport.closed == (1008, "authorization refused: the key is not known")
    assert client.ops("status")[-1]["message"] == "authorization refused: the key is not known"


# -- messages and time ---------------------------------------------------------------------------


def test_messages_are_the_cdr_the_recorder_writes_after_a_time_frame(graph, fox, timers):
    """A subscription's messages are MessageData frames with the message's CDR (the
    same bytes object the recorder writes), stamped with graph time, each new instant
    announced by a Time frame first; when the clock goes back (a new episode), time
    is announced again."""
    pub = graph.create_node("/robot").advertise("/odom", "nav_msgs/msg/Odometry")
    client = fox()
    odom = client.channel("/odom", client.frames())
    client.send({"op": "subscribe", "subscriptions": [{"id": 9, "channelId": odom}]})
    timers.advance(1.5)
    first = pub.publish({"child_frame_id": "a"})
    second = pub.publish({"child_frame_id": "b"})  # the same instant: no second Time
    timers.advance(0.5)
    third = pub.publish({"child_frame_id": "c"})
    frames = client.frames()
    assert frames == [
        ("time", 1_500_000_000),
        ("message", 9, 1_500_000_000, first.cdr()),
        ("message", 9, 1_500_000_000, second.cdr()),
        ("time", 2_000_000_000),
        ("message", 9, 2_000_000_000, third.cdr()),
    ]
    timers.now = 0.25  # the simulation starts again
    again = pub.publish({"child_frame_id": "d"})
    assert client.frames() == [("time", 250_000_000), ("message", 9, 250_000_000, again.cdr())]


def test_subscription_mistakes_are_told_in_statuses(graph, fox):
    graph.create_node("/robot").advertise("/odom", "nav_msgs/msg/Odometry")
    client = fox()
    odom = client.channel("/odom", client.frames())
    client.send(
        {
            "op": "subscribe",
            "subscriptions": [
                {"id": 1, "channelId": odom},
                {"id": 1, "channelId": odom},
                {"id": 2, "channelId": odom},
                {"id": 3, "channelId": 999},
            ],
        }
    )
    client.send({"op": "unsubscribe", "subscriptionIds": [1, 42]})
    assert [s["message"] for s in client.ops("status")] == [
        "subscribe: subscription id 1 is in use",
        "subscribe: /odom is subscribed already",
        "subscribe: no channel with id 999",
        "unsubscribe: no subscription with id 42",
    ]


def test_a_client_that_does_not_read_its_replies_is_closed(graph, fox):
    """Control frames (answers, statuses) are never dropped: past the outbox's bound the
    client is disconnected, and the status that would say why is not queued too."""
    client = fox(BridgeConfig(max_queue_bytes=100_000))
    for _ in range(500):
        client.send({"op": "getParameters", "parameterNames": [], "id": "x" * 200})
    assert client.transport.closed == (1008, "the client does not read its replies")


def test_a_client_that_does_not_read_keeps_two_camera_frames(graph, fox):
    """A channel with bytes in it (a camera) keeps the two newest messages for a client
    that does not read; the robot's publishing never waits, and the queue's bytes are
    the frames' CDR."""
    pub = graph.create_node("/robot").advertise("/camera/image/compressed", IMAGE)
    client = fox()
    camera = client.channel("/camera/image/compressed", client.frames())
    client.send({"op": "subscribe", "subscriptions": [{"id": 0, "channelId": camera}]})
    sent = [pub.publish({"format": "jpeg", "data": bytes([i]) * 10_000}) for i in range(50)]
    outbox = client.session.outbox
    assert outbox.topic_bytes == 2 * (len(sent[-1].cdr()) + 13)
    messages = [f for f in client.frames() if f[0] == "message"]
    assert [m[3] for m in messages] == [sent[-2].cdr(), sent[-1].cdr()]


def test_the_outbox_bound_holds_over_all_channels(graph, fox):
    pub = graph.create_node("/robot").advertise("/chatter", "std_msgs/msg/String")
    client = fox(BridgeConfig(max_queue_bytes=100_000))
    chatter = client.channel("/chatter", client.frames())
    client.send({"op": "subscribe", "subscriptions": [{"id": 0, "channelId": chatter}]})
    for _ in range(1000):
        pub.publish({"data": "x" * 500})
    assert client.session.outbox.topic_bytes <= 100_000
    assert client.session.outbox.dropped > 0


# -- client publishing ----------------------------------------------------------------------------


def twist_cdr(graph: Graph, x: float) -> bytes:
    codec = graph.codec(TWIST)
    return codec.to_cdr(codec.normalize({"linear": {"x": x}}, graph.now))


@pytest.mark.parametrize("encoding", ["cdr", "json"])
def test_a_client_publishes_on_its_channel_in_cdr_or_json(graph, fox, encoding):
    got: list[Any] = []
    graph.create_node("/robot").subscribe("/cmd_vel", TWIST, got.append)
    client = fox()
    client.frames()
    client.send(
        {
            "op": "advertise",
            "channels": [
                {
                    "id": 5,
                    "topic": "/cmd_vel",
                    "encoding": encoding,
                    "schemaName": "geometry_msgs/Twist",
                }
            ],
        }
    )
    payload = twist_cdr(graph, 0.5) if encoding == "cdr" else b'{"linear": {"x": 0.5}}'
    client.send(wire.client_message(5, payload))
    assert [m.data["linear"]["x"] for m in got] == [0.5]
    assert got[0].cdr() == twist_cdr(graph, 0.5)
    assert client.ops("status") == []


@pytest.mark.parametrize(
    ("channel", "payload", "said"),
    [
        (5, b"\x00\x01", "/cmd_vel: the bytes are not a CDR geometry_msgs/msg/Twist"),
        (6, b"[1, 2]", "/cmd_vel: a geometry_msgs/msg/Twist must be a JSON object"),
        (6, b'{"linear": {"x": "fast"}}', "/cmd_vel.linear.x"),
        (7, b"{}", "a message on channel 7, which was not advertised"),
    ],
    ids=["bad-cdr", "json-not-object", "json-wrong-type", "unadvertised"],
)
def test_a_bad_client_message_is_refused_in_a_status(graph, fox, channel, payload, said):
    got: list[Any] = []
    graph.create_node("/robot").subscribe("/cmd_vel", TWIST, got.append)
    client = fox()
    client.frames()
    client.send(
        {
            "op": "advertise",
            "channels": [
                {"id": 5, "topic": "/cmd_vel", "encoding": "cdr", "schemaName": TWIST},
                {"id": 6, "topic": "/cmd_vel", "encoding": "json", "schemaName": TWIST},
            ],
        }
    )
    client.send(wire.client_message(channel, payload))
    assert got == []
    [status] = client.ops("status")
    assert status["level"] == 2 and said in status["message"]


def test_a_client_may_not_advertise_what_it_may_not_publish(graph, fox):
    graph.create_node("/robot").advertise("/odom", "nav_msgs/msg/Odometry", own=True)
    client = fox()
    client.frames()
    client.send(
        {
            "op": "advertise",
            "channels": [
                {
                    "id": 1,
                    "topic": "/odom",
                    "encoding": "cdr",
                    "schemaName": "nav_msgs/msg/Odometry",
                },
                {"id": 2, "topic": "/protected/x", "encoding": "cdr", "schemaName": TWIST},
                {"id": 3, "topic": "/y", "encoding": "ros1", "schemaName": TWIST},
                {"id": 4, "topic": "/z", "encoding": "cdr", "schemaName": "not a type"},
            ],
        }
    )
    messages = [s["message"] for s in client.ops("status")]
    assert messages[0].startswith("advertise: /odom: topic /odom belongs to the lab")
    assert messages[1] == "advertise: /protected/x: /protected/x is protected"
    assert messages[2] == "advertise: /y: encoding 'ros1' is not one of cdr, json"
    assert messages[3] == "advertise: /z: 'not a type' is not a message type's name"


# -- services -------------------------------------------------------------------------------------


def services_of(client: Fox, frames: list[Any]) -> dict[str, int]:
    return {
        s["name"]: s["id"] for f in frames if f["op"] == "advertiseServices" for s in f["services"]
    }


def test_a_call_is_answered_in_its_encoding(graph, fox):
    client = fox()
    ids = services_of(client, client.frames())
    call = ids["/rosapi/get_ros_version"]
    client.send(wire.service_call_request(call, 1, "json", b""))
    client.send(wire.service_call_request(call, 2, "cdr", b"\x00\x01\x00\x00\x00"))
    json_answer, cdr_answer = client.frames()
    assert json_answer[:4] == ("response", call, 1, "json")
    assert orjson.loads(json_answer[4]) == {"version": 2, "distro": "jazzy"}
    assert cdr_answer[:4] == ("response", call, 2, "cdr")
    codec = graph.codec("rosapi_msgs/srv/GetROSVersion_Response")
    assert cdr_answer[4] == codec.to_cdr({"version": 2, "distro": "jazzy"})


def test_a_call_that_is_not_answered_in_time_fails(graph, fox, timers):
    graph.create_node("/slow").provide_service("/slow", "std_srvs/srv/Trigger", lambda call: None)
    client = fox(BridgeConfig(service_timeout=2))
    ids = services_of(client, client.frames())
    client.send(wire.service_call_request(ids["/slow"], 7, "json", b"{}"))
    client.send(wire.service_call_request(ids["/slow"], 8, "xml", b"<a/>"))
    timers.advance(2.1)
    assert client.ops("serviceCallFailure") == [
        {
            "op": "serviceCallFailure",
            "serviceId": ids["/slow"],
            "callId": 8,
            "message": "/slow: encoding 'xml' is not one of cdr, json",
        },
        {
            "op": "serviceCallFailure",
            "serviceId": ids["/slow"],
            "callId": 7,
            "message": "/slow did not answer within 2 s",
        },
    ]


# -- parameters and the connection graph -----------------------------------------------------------


def test_parameters_are_read_and_never_set(graph, fox):
    graph.parameters = lambda: {"camera_width": 320, "time_limit": 180.0}
    graph.params["/from_rosapi"] = '"hello"'
    client = fox()
    client.frames()
    client.send({"op": "getParameters", "parameterNames": [], "id": "a"})
    client.send({"op": "setParameters", "parameters": [{"name": "camera_width", "value": 1}]})
    client.send({"op": "subscribeParameterUpdates", "parameterNames": ["camera_width"]})
    frames = client.frames()
    assert frames[0] == {
        "op": "parameterValues",
        "parameters": [
            {"name": "/from_rosapi", "value": "hello"},
            {"name": "camera_width", "value": 320},
            {"name": "time_limit", "value": 180.0, "type": "float64"},
        ],
        "id": "a",
    }
    assert frames[1]["level"] == 2 and "read-only" in frames[1]["message"]
    assert frames[2] == {
        "op": "parameterValues",
        "parameters": [{"name": "camera_width", "value": 320}],
    }
    assert frames[3]["level"] == 1 and "do not change" in frames[3]["message"]


def test_the_connection_graph_is_sent_whole_then_as_changes(graph, fox, timers):
    robot = graph.create_node("/robot")
    robot.advertise("/odom", "nav_msgs/msg/Odometry")
    client = fox()
    client.frames()
    client.send({"op": "subscribeConnectionGraph"})
    [whole] = client.ops("connectionGraphUpdate")
    assert {"name": "/odom", "publisherIds": ["/robot"]} in whole["publishedTopics"]
    assert whole["removedTopics"] == [] and whole["removedServices"] == []
    listener = graph.create_node("/listener")
    sub = listener.subscribe("/odom", None, lambda m: None)
    timers.advance(0)
    [change] = client.ops("connectionGraphUpdate")
    assert change == {
        "op": "connectionGraphUpdate",
        "publishedTopics": [],
        "subscribedTopics": [{"name": "/odom", "subscriberIds": ["/listener"]}],
        "advertisedServices": [],
        "removedTopics": [],
        "removedServices": [],
    }
    sub.close()
    robot.destroy()
    timers.advance(0)
    updates = client.ops("connectionGraphUpdate")
    assert updates[-1]["removedTopics"] == ["/odom"]
    client.send({"op": "unsubscribeConnectionGraph"})
    graph.create_node("/more").advertise("/more", "std_msgs/msg/String")
    timers.advance(0)
    assert client.ops("connectionGraphUpdate") == []


# -- the wire ----------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("offered", "chosen"),
    [
        (["foxglove.sdk.v1"], "foxglove.sdk.v1"),
        (["foxglove.websocket.v1"], "foxglove.websocket.v1"),
        (["foxglove.websocket.v1", "foxglove.sdk.v1"], "foxglove.sdk.v1"),
        (["chat"], None),
        ([], None),
    ],
)
def test_the_subprotocol_chosen(offered, chosen):
    assert wire.select(offered) == chosen


@pytest.mark.parametrize(
    ("text", "said"),
    [
        ("nope", "the frame is not JSON"),
        ("[1]", "a frame must be a JSON object, got an array"),
        ('{"x": 1}', "the frame has no 'op' field"),
        ('{"op": []}', "'op' must be a string, got an array"),
        ('{"op": "publish"}', "'publish' is not an op of Foxglove's protocol that the lab takes"),
        ('{"op": "subscribe"}', "subscribe: object missing required field subscriptions"),
        (
            '{"op": "unsubscribe", "subscriptionIds": ["a"]}',
            "unsubscribe.subscriptionIds[0]: expected int, got str",
        ),
    ],
)
def test_a_bad_text_frame_says_what_is_wrong(text, said):
    with pytest.raises(FrameError) as caught:
        wire.parse_text(text)
    assert said in str(caught.value)


@pytest.mark.parametrize(
    ("data", "said"),
    [
        (b"", "an empty binary frame"),
        (b"\x01\x00", "has no channel id"),
        (b"\x02\x01\x00\x00\x00", "cut short"),
        (b"\x02" + struct.pack("<III", 1, 1, 50) + b"cdr", "runs past its end"),
        (b"\x03" + bytes(20), "a live robot plays nothing back"),
        (b"\x09", "binary opcode 0x09 is not one the lab takes"),
    ],
)
def test_a_bad_binary_frame_says_what_is_wrong(data, said):
    with pytest.raises(FrameError) as caught:
        wire.parse_binary(data)
    assert said in str(caught.value)
