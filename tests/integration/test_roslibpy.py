"""The real roslibpy 2.x, unmodified, against a real bridge server.

roslibpy runs Twisted's reactor in a thread that can start only once per process,
so connections are closed after each test but the reactor is never stopped.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterator
from typing import Any

import pytest
import roslibpy
from roslibpy.core import ServiceException

pytestmark = pytest.mark.integration
WAIT = 10.0


@pytest.fixture
def ros(server) -> Iterator[Callable[[], roslibpy.Ros]]:
    """Open roslibpy connections to the test server; all are closed afterwards."""
    opened: list[roslibpy.Ros] = []

    def connect() -> roslibpy.Ros:
        client = roslibpy.Ros(host="127.0.0.1", port=server.port)
        client.run(timeout=WAIT)
        assert client.is_connected
        opened.append(client)
        return client

    yield connect
    for client in opened:
        client.close()


class Inbox:
    """Collects callback values; ``wait(n)`` blocks until n have arrived."""

    def __init__(self) -> None:
        self.items: list[Any] = []
        self._cond = threading.Condition()

    def __call__(self, item: Any) -> None:
        with self._cond:
            self.items.append(item)
            self._cond.notify_all()

    def wait(self, count: int = 1) -> list[Any]:
        with self._cond:
            assert self._cond.wait_for(lambda: len(self.items) >= count, WAIT), self.items
            return list(self.items)


def wait_subscribed(server, topic: str, count: int = 1) -> None:
    """Block until the graph shows ``count`` subscriptions on ``topic``."""
    topics = server.lab.graphs["playground"].topics
    server.wait_until(lambda: topic in topics and len(topics[topic].subscriptions) >= count)


def test_two_clients_publish_and_subscribe(ros, server):
    """Messages published by one roslibpy client reach another, in order, with defaults filled."""
    talker, listener = ros(), ros()
    inbox = Inbox()
    roslibpy.Topic(listener, "/cmd_vel", "geometry_msgs/Twist").subscribe(inbox)
    wait_subscribed(server, "/cmd_vel")
    topic = roslibpy.Topic(talker, "/cmd_vel", "geometry_msgs/Twist")
    for x in range(5):
        topic.publish(roslibpy.Message({"linear": {"x": float(x)}}))
    got = inbox.wait(5)
    assert [m["linear"]["x"] for m in got] == [0.0, 1.0, 2.0, 3.0, 4.0]
    assert got[0]["angular"] == {"x": 0.0, "y": 0.0, "z": 0.0}


def test_rosapi_calls(ros):
    """roslibpy's introspection helpers get answers from the lab's rosapi."""
    client = ros()
    roslibpy.Topic(client, "/chatter", "std_msgs/String").advertise()
    assert "/rosapi/topics" in client.get_services()
    topics = client.get_topics()
    assert "/chatter" in topics
    assert client.get_topic_type("/chatter") == "std_msgs/msg/String"
    assert "/rosapi" in client.get_nodes()
    details = client.get_message_details("geometry_msgs/Twist")
    assert details["typedefs"][0]["fieldnames"] == ["linear", "angular"]
    assert client.get_service_type("/rosapi/topics") == "rosapi_msgs/srv/Topics"
    assert client.get_time().secs > 1_700_000_000


def test_rosout_is_listed_on_a_fresh_server(ros, server):
    """/rosout is there before anything was logged, as on any ROS 2 system."""
    client = ros()
    assert "/rosout" in client.get_topics()
    assert client.get_topic_type("/rosout") == "rcl_interfaces/msg/Log"
    assert "/rosout" in client.get_node_details("/labd")["publishing"]  # the lab's log


def test_params(ros):
    """roslibpy's Param set/get/delete round-trips JSON values."""
    param = roslibpy.Param(ros(), "gains")
    param.set({"p": 1.5, "i": [1, 2]})
    assert param.get() == {"p": 1.5, "i": [1, 2]}
    param.delete()
    assert param.get() is None


def test_service_provided_by_one_client_called_by_another(ros):
    """A service advertised by one roslibpy client answers another's calls, and failures fail."""
    provider, caller = ros(), ros()
    ready = Inbox()

    def add(request: dict[str, Any], response: dict[str, Any]) -> bool:
        if request["a"] < 0:
            return False
        response["sum"] = request["a"] + request["b"]
        return True

    service = roslibpy.Service(provider, "/add_two_ints", "example_interfaces/AddTwoInts")
    service.advertise(add)
    # The advertisement is in flight; a blocking call of rosapi on the same connection
    # returns only after the bridge has handled it (frames are handled in order).
    provider.get_services(ready)
    assert "/add_two_ints" in ready.wait()[0]["services"]
    client = roslibpy.Service(caller, "/add_two_ints", "example_interfaces/AddTwoInts")
    assert client.call(roslibpy.ServiceRequest({"a": 40, "b": 2}), timeout=WAIT) == {"sum": 42}
    with pytest.raises(ServiceException):
        client.call(roslibpy.ServiceRequest({"a": -1, "b": 2}), timeout=WAIT)


def test_lab_service_called_from_roslibpy(ros, server):
    """A service provided inside the lab (as /lab/step will be) is called from roslibpy."""

    def setup() -> None:
        node = server.lab.graphs["playground"].create_node("/robot")
        node.provide_service(
            "/reset",
            "std_srvs/srv/Trigger",
            lambda call: call.reply({"success": True, "message": "reset"}),
        )

    server.call(setup)
    service = roslibpy.Service(ros(), "/reset", "std_srvs/srv/Trigger")
    assert service.call(roslibpy.ServiceRequest(), timeout=WAIT) == {
        "success": True,
        "message": "reset",
    }


def test_action_goal_feedback_result(ros, server):
    """roslibpy's ActionClient gets feedback and the result of a goal served in the lab."""

    def setup() -> None:
        def serve(goal: Any) -> None:
            sequence = [0, 1]
            for _ in range(goal.goal.data["order"] - 2):
                sequence.append(sequence[-1] + sequence[-2])
                goal.feedback({"sequence": sequence})
            goal.finish(4, {"sequence": sequence})

        node = server.lab.graphs["playground"].create_node("/fib_server")
        node.provide_action("/fibonacci", "example_interfaces/action/Fibonacci", serve)

    server.call(setup)
    client = roslibpy.ActionClient(ros(), "/fibonacci", "example_interfaces/action/Fibonacci")
    results, feedback, errors = Inbox(), Inbox(), Inbox()
    goal_id = client.send_goal(roslibpy.Goal({"order": 5}), results, feedback, errors)
    client.wait_goal(goal_id, timeout=WAIT)
    assert errors.items == []
    assert results.wait()[0]["values"] == {"sequence": [0, 1, 1, 2, 3]}
    assert [f["sequence"] for f in feedback.wait(3)][-1] == [0, 1, 1, 2, 3]


def test_client_leaving_is_cleaned_up(ros, server):
    """When a roslibpy client closes, its topics and services vanish from the graph."""
    client = ros()
    roslibpy.Topic(client, "/gone", "std_msgs/String").advertise()
    roslibpy.Service(client, "/gone_srv", "std_srvs/Trigger").advertise(lambda a, b: True)
    seen = Inbox()
    client.get_services(seen)
    seen.wait()
    graph = server.lab.graphs["playground"]
    assert server.call(lambda: "/gone" in graph.topics and "/gone_srv" in graph.services)
    client.close()
    server.wait_until(lambda: "/gone" not in graph.topics and "/gone_srv" not in graph.services)
