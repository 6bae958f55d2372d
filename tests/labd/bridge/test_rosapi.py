"""The /rosapi services, answered from the graph, under absolute and relative names."""

from __future__ import annotations

import orjson
import pytest


def call(client, service, args=None):
    client.send({"op": "call_service", "id": "r", "service": service, "args": args or {}})
    (reply,) = [f for f in client.frames() if f["op"] == "service_response"]
    assert reply["result"] is True, reply
    return reply["values"]


@pytest.fixture
def busy(connect, graph):
    """A graph with a publisher, a subscriber, a service and an action."""
    robot = graph.create_node("/robot")
    robot.advertise("/odom", "nav_msgs/msg/Odometry")
    robot.subscribe("/cmd_vel", "geometry_msgs/msg/Twist", lambda m: None)
    robot.provide_service("/reset", "std_srvs/srv/Trigger", lambda call: call.reply({}))
    robot.provide_action("/fib", "example_interfaces/action/Fibonacci", lambda goal: None)
    return connect()


@pytest.mark.parametrize("name", ["/rosapi/topics", "rosapi/topics"])
def test_topics_under_absolute_and_relative_names(busy, name):
    """rosapi/topics lists topics with their types, whichever way the name is spelled."""
    values = call(busy, name)
    pairs = dict(zip(values["topics"], values["types"], strict=True))
    assert pairs["/odom"] == "nav_msgs/msg/Odometry"
    assert pairs["/cmd_vel"] == "geometry_msgs/msg/Twist"


def test_topic_questions(busy):
    """topic_type, topics_for_type, publishers and subscribers describe the graph."""
    assert call(busy, "/rosapi/topic_type", {"topic": "/odom"}) == {"type": "nav_msgs/msg/Odometry"}
    assert call(busy, "/rosapi/topic_type", {"topic": "/none"}) == {"type": ""}
    assert call(busy, "/rosapi/topics_for_type", {"type": "geometry_msgs/Twist"}) == {
        "topics": ["/cmd_vel"]
    }
    assert call(busy, "/rosapi/publishers", {"topic": "/odom"}) == {"publishers": ["/robot"]}
    assert call(busy, "/rosapi/subscribers", {"topic": "cmd_vel"}) == {"subscribers": ["/robot"]}


def test_service_and_action_questions(busy):
    """services, service_type, service_node and action_servers describe what is provided."""
    services = call(busy, "/rosapi/services")["services"]
    assert "/reset" in services and "/rosapi/topics" in services
    assert call(busy, "/rosapi/service_type", {"service": "/reset"}) == {
        "type": "std_srvs/srv/Trigger"
    }
    assert call(busy, "/rosapi/service_node", {"service": "/reset"}) == {"node": "/robot"}
    assert call(busy, "/rosapi/services_for_type", {"type": "std_srvs/Trigger"}) == {
        "services": ["/reset"]
    }
    assert call(busy, "/rosapi/action_servers") == {"action_servers": ["/fib"]}


def test_nodes_and_node_details(busy):
    """nodes lists every node; node_details says what one publishes, subscribes and serves."""
    nodes = call(busy, "/rosapi/nodes")["nodes"]
    assert {"/robot", "/rosapi", "/bridge/client_1"} <= set(nodes)
    assert call(busy, "/rosapi/node_details", {"node": "/robot"}) == {
        "subscribing": ["/cmd_vel"],
        "publishing": ["/odom"],
        "services": ["/fib/_action/cancel_goal", "/reset"],  # an action's, as in ROS 2
    }


def test_type_details(busy):
    """message_details and the service details give typedefs of the type and its parts."""
    typedefs = call(busy, "/rosapi/message_details", {"type": "geometry_msgs/Twist"})["typedefs"]
    assert [t["type"] for t in typedefs] == ["geometry_msgs/msg/Twist", "geometry_msgs/msg/Vector3"]
    assert typedefs[1]["fieldnames"] == ["x", "y", "z"]
    assert typedefs[1]["fieldtypes"] == ["float64"] * 3
    request = call(
        busy, "/rosapi/service_request_details", {"type": "example_interfaces/AddTwoInts"}
    )
    assert request["typedefs"][0]["fieldnames"] == ["a", "b"]
    response = call(busy, "/rosapi/service_response_details", {"type": "std_srvs/srv/Trigger"})
    assert response["typedefs"][0]["fieldnames"] == ["success", "message"]
    raw = call(busy, "/rosapi/topics_and_raw_types")
    odom = raw["typedefs_full_text"][raw["topics"].index("/odom")]
    assert "MSG: geometry_msgs/PoseWithCovariance" in odom


def test_unknown_type_is_a_failed_call(busy):
    """Asking about a type that does not exist fails the call with the reason."""
    busy.send(
        {
            "op": "call_service",
            "id": 1,
            "service": "/rosapi/message_details",
            "args": {"type": "no/Such"},
        }
    )
    (reply,) = busy.frames()
    assert reply["result"] is False and "unknown message type 'no/Such'" in reply["values"]


def test_params_round_trip_as_json_text(busy):
    """set_param stores JSON text; get_param, has_param, names and delete see it."""
    call(busy, "/rosapi/set_param", {"name": "gain", "value": orjson.dumps([1, 2]).decode()})
    assert orjson.loads(call(busy, "/rosapi/get_param", {"name": "gain"})["value"]) == [1, 2]
    assert call(busy, "/rosapi/has_param", {"name": "gain"}) == {"exists": True}
    assert call(busy, "/rosapi/get_param_names") == {"names": ["gain"]}
    call(busy, "/rosapi/delete_param", {"name": "gain"})
    assert call(busy, "/rosapi/get_param", {"name": "gain", "default_value": "3"}) == {"value": "3"}
    assert call(busy, "/rosapi/get_param", {"name": "gain"}) == {"value": "null"}


def test_time_and_version(busy, timers):
    """get_time gives graph time (with the ROS 1 names for roslibpy); the version is 2 / jazzy."""
    timers.advance(12.5)
    assert call(busy, "/rosapi/get_time") == {
        "time": {"sec": 12, "nanosec": 500_000_000, "secs": 12, "nsecs": 500_000_000}
    }
    assert call(busy, "/rosapi/get_ros_version") == {"version": 2, "distro": "jazzy"}


def test_rosout_is_listed_before_anything_is_logged(connect):
    """A graph has /rosout from its creation, published by the lab's /labd node."""
    client = connect()
    values = call(client, "rosapi/topics")
    assert dict(zip(values["topics"], values["types"], strict=True))["/rosout"] == (
        "rcl_interfaces/msg/Log"
    )
    assert call(client, "/rosapi/publishers", {"topic": "/rosout"}) == {"publishers": ["/labd"]}
