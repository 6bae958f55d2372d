"""Rules that hold for every op: authorization, protected names, errors, limits, status."""

from __future__ import annotations

import orjson
import pytest

from labd.bridge.ops.fragments import Fragments
from labd.bridge.ops.topics import Topics
from labd.bridge.render import fragment
from labd.config import BridgeConfig


def status_client(connect, config=None, **kwargs):
    client = connect(config, **kwargs)
    client.send({"op": "set_level", "level": "info"})
    client.frames()
    return client


# -- authorization -----------------------------------------------------------------------


def test_first_frame_must_be_auth_when_required(connect):
    """With an authorizer, any other first frame closes the connection (1008)."""
    client = connect(auth_required=True)
    client.send({"op": "subscribe", "topic": "/x", "type": "std_msgs/String"})
    assert client.transport.closed is not None
    assert client.transport.closed[0] == 1008 and "auth" in client.transport.closed[1]
    assert client.transport.keys == []


@pytest.mark.parametrize("frame", [{"op": "auth", "key": "k1"}, {"op": "auth", "mac": "k1"}])
def test_auth_frame_key_goes_to_the_authorizer(connect, frame):
    """The key from an auth frame (or rosauth's mac field) is what gets authorized."""
    client = connect(auth_required=True)
    client.send(frame)
    assert client.transport.keys == ["k1"]
    assert client.transport.closed is None


def test_frames_wait_for_the_grant_and_time_runs_out(connect, timers):
    """Frames sent while the key is checked are handled after the grant; expiry closes."""
    client = connect(auth_required=True)
    client.send({"op": "auth", "key": "k"})
    client.send({"op": "call_service", "id": 1, "service": "/rosapi/get_ros_version"})
    assert client.frames() == []
    client.session.grant(30)
    assert client.frames()[0]["values"] == {"version": 2, "distro": "jazzy"}
    timers.advance(29)
    assert client.transport.closed is None
    timers.advance(2)
    assert client.transport.closed == (1008, "the authorization has expired")


def test_url_key_needs_no_auth_frame(connect):
    """A key in the URL query is checked at once; the client may then send ops."""
    client = connect(auth_required=True, url_key="from-url")
    assert client.transport.keys == ["from-url"]
    client.session.grant(10)
    client.send({"op": "call_service", "id": 1, "service": "/rosapi/nodes"})
    assert client.frames()[0]["result"] is True


def test_refused_key_closes(connect):
    """A refused key closes the connection with the authorizer's reason."""
    client = connect(auth_required=True)
    client.send({"op": "auth", "key": "bad"})
    client.session.refuse("the key is not known")
    assert client.transport.closed == (1008, "authorization refused: the key is not known")


def test_silent_client_is_closed_after_the_auth_timeout(connect, timers):
    """A client that never authorizes is disconnected after auth_timeout."""
    client = connect(BridgeConfig(auth_timeout=3), auth_required=True)
    timers.advance(3.1)
    assert client.transport.closed == (1008, "no authorization in time")


# -- protected names --------------------------------------------------------------------------


def test_protected_topics_never_cross(connect, graph):
    """Messages on /protected names neither reach clients nor come from them."""
    secret = graph.create_node("/robot").advertise("/protected/pose", "geometry_msgs/msg/Pose")
    client = status_client(connect)
    client.send({"op": "subscribe", "topic": "/protected/pose", "type": "geometry_msgs/Pose"})
    client.send({"op": "advertise", "topic": "protected/cmd", "type": "std_msgs/String"})
    secret.publish({})
    frames = client.frames()
    assert [f["op"] for f in frames] == ["status", "status"]
    assert all("is protected" in f["msg"] for f in frames)
    assert "/protected/cmd" not in graph.topics


def test_protected_service_calls_return_empty(connect):
    """A call on a protected service answers {} (the rosjs rule) without reaching anyone."""
    client = connect()
    client.send({"op": "call_service", "id": "p", "service": "/protected/reset"})
    (reply,) = client.frames()
    assert reply == {
        "op": "service_response",
        "service": "/protected/reset",
        "values": {},
        "result": True,
        "id": "p",
    }


def test_protected_names_are_hidden_from_rosapi(connect, graph):
    """rosapi lists leave out protected topics, so clients cannot learn they exist."""
    robot = graph.create_node("/robot")
    robot.advertise("/protected/pose", "geometry_msgs/msg/Pose")
    robot.advertise("/pose", "geometry_msgs/msg/Pose")
    client = connect()
    client.send({"op": "call_service", "id": 1, "service": "/rosapi/topics"})
    topics = client.frames()[0]["values"]["topics"]
    assert "/pose" in topics and "/protected/pose" not in topics


def test_protected_prefix_is_configurable(connect, graph):
    """With another prefix, /protected is an ordinary name and the new prefix is guarded."""
    client = connect(BridgeConfig(protected_prefixes=("/private",)))
    graph.create_node("/robot").advertise("/protected/pose", "geometry_msgs/msg/Pose")
    client.send({"op": "subscribe", "topic": "/protected/pose"})
    client.send({"op": "call_service", "id": 1, "service": "/private/x"})
    assert client.frames()[0]["values"] == {}
    assert len(graph.topics["/protected/pose"].subscriptions) == 1


# -- bad input ------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("frame", "expected"),
    [
        ("{not json", "the frame is not JSON"),
        ("[1, 2]", "a frame must be a JSON object"),
        ('{"topic": "/x"}', "the frame has no 'op' field"),
        ('{"op": "dance"}', "unknown op 'dance'"),
        ('{"op": "subscribe", "topic": 7}', "subscribe.topic must be a string"),
        ('{"op": "subscribe", "topic": "/x", "type": "nope/Nope"}', "unknown message type"),
        ('{"op": "subscribe", "topic": "a//b", "type": "std_msgs/String"}', "invalid name"),
        (b"\x00\xff\xfe garbage", "the frame is not JSON"),
        ('{"op": "publish", "topic": "/never"}', "advertise it with its type"),
    ],
)
def test_bad_frames_get_a_status_and_the_connection_carries_on(connect, frame, expected):
    """Each malformed frame is answered by an error status; the next good frame still works."""
    client = status_client(connect)
    client.send(frame)
    (status,) = client.frames()
    assert status["op"] == "status" and status["level"] == "error"
    assert expected in status["msg"]
    client.send({"op": "call_service", "id": 1, "service": "/rosapi/get_ros_version"})
    assert client.frames()[0]["result"] is True


def test_status_carries_the_op_id(connect):
    """A status caused by an op with an id carries that id."""
    client = status_client(connect)
    client.send({"op": "subscribe", "id": "mine", "topic": 3})
    assert client.frames()[0]["id"] == "mine"


def test_status_levels_filter(connect):
    """At level error, warnings and infos are not sent; at warning, infos are not."""
    client = connect()
    client.send({"op": "set_level", "level": "error"})
    client.send({"op": "unsubscribe", "topic": "/not_subscribed"})  # a warning
    assert client.frames() == []
    client.send({"op": "set_level", "level": "warning"})
    client.send({"op": "unsubscribe", "topic": "/not_subscribed"})
    (warning,) = client.frames()
    assert warning["level"] == "warning"


def test_oversized_frame_is_dropped_not_fatal(connect):
    """A frame over max_message_size is refused with a status; the connection stays."""
    client = status_client(connect, BridgeConfig(max_message_size=1000))
    client.send({"op": "publish", "topic": "/x", "msg": {"data": "x" * 2000}})
    (status,) = client.frames()
    assert "over the limit of 1000" in status["msg"]
    assert client.transport.closed is None


def test_subscription_limit(connect):
    """A client cannot hold more subscriptions than max_subscriptions."""
    client = status_client(connect, BridgeConfig(max_subscriptions=3))
    for i in range(5):
        client.send({"op": "subscribe", "id": i, "topic": f"/t{i}", "type": "std_msgs/String"})
    errors = [f for f in client.frames() if f["level"] == "error"]
    assert len(errors) == 2 and "too many subscriptions" in errors[0]["msg"]


def test_subscribe_unsubscribe_flood_leaves_nothing_behind(connect, graph):
    """Thousands of subscribe/unsubscribe pairs, each taken (the topic has the client's
    subscription in between), leave no subscription and no topic behind."""
    client = connect()
    for i in range(3000):
        topic = f"/flood{i % 7}"
        client.send({"op": "subscribe", "id": str(i), "topic": topic, "type": "std_msgs/String"})
        assert [s.node for s in graph.topics[topic].subscriptions] == [client.session.node]
        client.send({"op": "unsubscribe", "id": str(i), "topic": topic})
    assert client.frames() == []  # none refused
    assert not any(name.startswith("/flood") for name in graph.topics)
    assert client.session.capability(Topics).subscription_count == 0


def test_client_leaving_releases_everything(connect, graph):
    """After a client leaves, its node, topics, services and actions are gone from the graph."""
    client = status_client(connect)
    client.send({"op": "advertise", "topic": "/mine", "type": "std_msgs/String"})
    client.send({"op": "subscribe", "topic": "/theirs", "type": "std_msgs/String"})
    client.send({"op": "advertise_service", "service": "/svc", "type": "std_srvs/srv/Trigger"})
    client.send(
        {"op": "advertise_action", "action": "/act", "type": "example_interfaces/action/Fibonacci"}
    )
    assert [f["level"] for f in client.frames()] == ["info"] * 4
    node = client.session.node.name
    # Each of them is there, the client's, before it leaves.
    assert [p.node.name for p in graph.topics["/mine"].publishers] == [node]
    assert [s.node.name for s in graph.topics["/theirs"].subscriptions] == [node]
    assert graph.services["/svc"].node.name == graph.actions["/act"].node.name == node
    client.session.close()
    assert node not in graph.nodes
    assert "/mine" not in graph.topics and "/theirs" not in graph.topics
    assert "/svc" not in graph.services and "/act" not in graph.actions


def test_errors_are_published_on_rosout(connect):
    """Client errors go out on /rosout as rcl_interfaces/msg/Log, like a ROS node's log."""
    listener, clumsy = connect(), connect()
    listener.send({"op": "subscribe", "topic": "/rosout", "type": "rcl_interfaces/msg/Log"})
    clumsy.send({"op": "subscribe", "topic": 5})
    (log,) = listener.frames()
    assert log["msg"]["level"] == 40 and "subscribe.topic must be a string" in log["msg"]["msg"]


# -- fragments ------------------------------------------------------------------------------------


def test_fragments_reassemble_in_any_order(connect):
    """A frame sent in fragments, out of order, is handled once complete."""
    client = connect()
    text = orjson.dumps({"op": "call_service", "id": "f", "service": "/rosapi/get_ros_version"})
    parts = [orjson.loads(f.data) for f in fragment(text.decode(), 10, "frag-1")]
    for part in reversed(parts):
        assert client.frames() == []
        client.send(part)
    (reply,) = client.frames()
    assert reply["id"] == "f" and reply["result"] is True


def test_incomplete_fragments_expire(connect, timers):
    """A fragmented message whose parts stop coming is dropped after fragment_timeout."""
    client = status_client(connect, BridgeConfig(fragment_timeout=5))
    client.send({"op": "fragment", "id": "x", "data": "{", "num": 0, "total": 2})
    timers.advance(6)
    (status,) = client.frames()
    assert "only 1 of 2 parts arrived" in status["msg"]
    assert client.session.capability(Fragments).assemblies == {}


def test_outgoing_fragments_respect_fragment_size(connect):
    """With fragment_size, a long message arrives as fragments that join to the message."""
    sub, pub = connect(), connect()
    sub.send({"op": "subscribe", "topic": "/c", "type": "std_msgs/String", "fragment_size": 20})
    pub.send({"op": "advertise", "topic": "/c", "type": "std_msgs/String"})
    pub.send({"op": "publish", "topic": "/c", "msg": {"data": "a fairly long sentence " * 3}})
    parts = sub.frames()
    assert len(parts) > 1 and all(len(p["data"]) <= 20 for p in parts)
    assert [p["num"] for p in parts] == list(range(parts[0]["total"]))
    joined = orjson.loads("".join(p["data"] for p in parts))
    assert joined["msg"]["data"] == "a fairly long sentence " * 3
