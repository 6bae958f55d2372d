"""The real roslibjs (npm ``roslib`` 2.1.0, run by Node.js) against a real bridge.

Each test runs one scenario of a script in ``tests/js/`` against the ``server`` fixture:
the script drives unmodified roslibjs clients, bounds every wait, and prints what it
observed as JSON (``harness.mjs`` describes the contract); the assertions are here.
Typed arrays come back as ``{"typed_array": NAME, "values": [...]}``.
"""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path
from typing import TYPE_CHECKING, Any

import pytest

if TYPE_CHECKING:
    from tests.helpers.labs import ServerThread

JS = Path(__file__).resolve().parents[1] / "js"
NODE = shutil.which("node")
TIMEOUT = 60  # seconds for one script; its own waits are bounded far below this

pytestmark = [
    pytest.mark.integration,
    pytest.mark.skipif(NODE is None, reason="Node.js (node, version 20 or later) is not installed"),
]


def roslibjs(server: ServerThread, script: str, scenario: str) -> Any:
    """Run ``scenario`` of ``tests/js/<script>`` against ``server``; return its observations."""
    if not (JS / "node_modules" / "roslib").is_dir():
        pytest.fail(f"{JS / 'node_modules'} has no roslib: run `make setup` to install it")
    assert NODE is not None
    try:
        proc = subprocess.run(
            [NODE, str(JS / script), server.url, scenario],
            cwd=JS,
            capture_output=True,
            text=True,
            timeout=TIMEOUT,
            check=False,
        )
    except subprocess.TimeoutExpired as err:
        pytest.fail(f"{script} {scenario} ran over {TIMEOUT} s; stderr:\n{err.stderr}")
    assert proc.returncode == 0, (
        f"{script} {scenario} exited with {proc.returncode}:\n{proc.stderr}{proc.stdout}"
    )
    output = json.loads(proc.stdout)
    assert output["ros_errors"] == [], f"roslibjs reported errors: {output['ros_errors']}"
    return output["scenarios"][scenario]


def typed(name: str, values: list[Any]) -> dict[str, Any]:
    return {"typed_array": name, "values": values}


ZERO3 = {"x": 0, "y": 0, "z": 0}


# -- topics ------------------------------------------------------------------------------


def test_string_and_twist_cross_between_connections_with_defaults_filled(server):
    """Messages published by one roslibjs connection reach another, in order, defaults filled,
    and enter the lab's graph as typed values."""
    graph = server.lab.graphs["playground"]
    in_graph: list[dict[str, Any]] = []
    server.call(
        lambda: graph.create_node("/python_listener").subscribe(
            "/cmd_vel", "geometry_msgs/msg/Twist", lambda message: in_graph.append(message.data)
        )
    )
    seen = roslibjs(server, "topics.mjs", "pubsub")
    assert seen["chatter"] == [{"data": "one"}, {"data": "two"}, {"data": "three"}]
    assert seen["twist"] == [
        {"linear": {"x": 1.5, "y": 0, "z": 0}, "angular": {"x": 0, "y": 0, "z": -0.25}}
    ]
    assert seen["echoed"] == [{"data": f"echo: {w}"} for w in ("one", "two", "three")]
    # Delivery is synchronous, so the graph's subscriber had it before A did.
    received = server.call(lambda: list(in_graph))
    assert received == [
        {"linear": {"x": 1.5, "y": 0.0, "z": 0.0}, "angular": {"x": 0.0, "y": 0.0, "z": -0.25}}
    ]
    assert all(type(v) is float for part in received[0].values() for v in part.values())


def test_latched_message_reaches_a_later_subscriber(server):
    """A message published on a latched topic reaches a roslibjs client that subscribes later."""
    seen = roslibjs(server, "topics.mjs", "latched")
    assert seen["received"] == [{"data": "maze-7"}]


def test_throttle_rate_sends_the_first_and_the_newest_message(server):
    """A burst to a subscription with throttle_rate 1000 ms arrives as its first and last
    message, a throttle interval apart, while an unthrottled subscriber gets all ten."""
    seen = roslibjs(server, "topics.mjs", "throttle")
    assert seen["burst_ms"] < 900, "the burst itself took a throttle interval; the test is void"
    assert seen["unthrottled"] == [str(i) for i in range(10)]
    assert seen["throttled"] == ["0", "9"]
    (gap,) = seen["throttled_gaps_ms"]
    assert gap >= 900


def test_two_topic_objects_on_one_connection_each_get_every_message_once(server):
    """Two roslibjs Topic objects on one topic each see every message once, and unsubscribing
    one leaves the other subscribed."""
    seen = roslibjs(server, "topics.mjs", "two_topic_objects")
    assert seen["on_the_wire"] == ["x", "y", "z"]
    assert seen["first"] == ["x", "y"]
    assert seen["second"] == ["x", "y", "z"]


def test_unsubscribe_stops_delivery_to_the_socket(server):
    """After Topic.unsubscribe the bridge sends that client no more messages of the topic."""
    seen = roslibjs(server, "topics.mjs", "unsubscribe")
    assert seen["callback"] == [{"data": "before"}]
    assert seen["on_the_wire"] == [{"data": "before"}]


# -- compression -------------------------------------------------------------------------


def test_cbor_delivers_numeric_arrays_as_typed_arrays(server):
    """With compression cbor, roslibjs decodes binary frames whose numeric arrays keep their
    element type and values (float64 → Float64Array, uint8 → Uint8Array, int32 → Int32Array)."""
    seen = roslibjs(server, "encodings.mjs", "cbor")
    sent = seen["sent"]
    assert seen["frames"] == ["binary"] * 3
    assert seen["joints"] == {
        "header": sent["joints"]["header"],
        "name": sent["joints"]["name"],
        "position": typed("Float64Array", sent["joints"]["position"]),
        "velocity": typed("Float64Array", sent["joints"]["velocity"]),
        "effort": typed("Float64Array", []),
    }
    assert seen["image"]["data"] == typed("Uint8Array", sent["image"]["data"])
    assert {k: seen["image"][k] for k in ("height", "width", "encoding", "step")} == {
        k: sent["image"][k] for k in ("height", "width", "encoding", "step")
    }
    assert seen["ints"]["data"] == typed("Int32Array", sent["ints"]["data"])


def test_cbor_raw_hands_over_cdr_that_rosbags_reads(server):
    """With compression cbor-raw, roslibjs receives CDR bytes that decode to the message sent."""
    seen = roslibjs(server, "encodings.mjs", "cbor_raw")
    store = server.lab.types.typestore
    text = seen["chatter"]
    assert text["bytes"]["typed_array"] == "Uint8Array"
    assert isinstance(text["secs"], int) and isinstance(text["nsecs"], int)
    decoded = store.deserialize_cdr(bytes(text["bytes"]["values"]), "std_msgs/msg/String")
    assert decoded.data == "raw hello"
    raw = bytes(seen["joints"]["bytes"]["values"])
    joints = store.deserialize_cdr(raw, "sensor_msgs/msg/JointState")
    assert joints.name == ["shoulder", "elbow", "wrist"]
    assert joints.position.tolist() == [0.5, -1.25, 3.141592653589793]
    assert (joints.header.stamp.sec, joints.header.stamp.nanosec) == (12, 345)


def test_fragments_are_reassembled_by_roslibjs(server):
    """With fragment_size, messages (plain and png) arrive as fragments of at most that many
    characters, which roslibjs reassembles into the message sent."""
    seen = roslibjs(server, "encodings.mjs", "fragments")
    assert seen["plain"] == seen["packed"] == [{"data": seen["sent"]}]
    by_id: dict[str, list[dict[str, Any]]] = {}
    for part in seen["parts"]:
        by_id.setdefault(part["id"], []).append(part)
    assert len(by_id) == 2
    for parts in by_id.values():
        assert sorted(p["num"] for p in parts) == list(range(parts[0]["total"]))
        assert parts[0]["total"] > 1
        assert all(p["size"] <= 100 for p in parts)


def test_png_compression_delivers_the_message(server):
    """With compression png, every message arrives as a png op that roslibjs decodes intact."""
    seen = roslibjs(server, "encodings.mjs", "png")
    assert seen["frames"] == ["text:png"] * 3
    assert seen["chatter"] == [{"data": text} for text in seen["sent"]]
    assert seen["twist"] == [{"linear": {"x": 0.25, "y": 0, "z": 0}, "angular": {**ZERO3, "z": 1}}]


# -- status ------------------------------------------------------------------------------


def test_wrong_field_type_status_names_the_field_and_carries_the_publish_id(server):
    """After setStatusLevel('error'), each publish with a wrong field type gets an error status
    naming the field, with the publish's id, so roslibjs emits it as 'status:ID'."""
    seen = roslibjs(server, "status.mjs", "wrong_field_type")
    first, second = seen["statuses"]
    assert first["level"] == second["level"] == "error"
    assert "msg.data must be a string" in first["msg"]
    assert "msg.linear.x must be a number" in second["msg"]
    assert [first["id"], second["id"]] == seen["publish_ids"][:2]
    assert seen["routed"] == seen["statuses"]


def test_refused_publishes_reach_no_subscriber(server):
    """Publishes refused for a wrong field type reach no subscriber; the good one does."""
    seen = roslibjs(server, "status.mjs", "wrong_field_type")
    assert seen["heard"] == [{"data": "fine"}]


def test_no_status_without_set_level(server):
    """A roslibjs client that never called setStatusLevel receives no status frames."""
    seen = roslibjs(server, "status.mjs", "wrong_field_type")
    assert seen["statuses_without_set_level"] == []


# -- services ----------------------------------------------------------------------------


def test_service_advertised_by_one_connection_answers_another(server):
    """A roslibjs-advertised AddTwoInts answers another connection's calls, by absolute and
    relative name, with missing request fields defaulted."""
    seen = roslibjs(server, "services.mjs", "add_two_ints")
    assert seen["answer"] == {"ok": True, "value": {"sum": 42}}
    assert seen["relative"] == {"ok": True, "value": {"sum": -7}}
    assert seen["requests"] == [{"a": 2, "b": 40}, {"a": -7, "b": 0}]


def test_callback_returning_false_reaches_the_callers_failed_callback(server):
    """A service callback that returns false makes the caller's failedCallback run."""
    seen = roslibjs(server, "services.mjs", "returns_false")
    assert seen["ok"] is False
    assert "/refuse" in seen["error"]


def test_advertise_async_that_throws_reaches_the_failed_callback_with_its_message(server):
    """An advertiseAsync callback that throws fails the call with the error's text."""
    seen = roslibjs(server, "services.mjs", "async_throws")
    assert seen["ok"] is False
    assert "motor is on fire (data=true)" in seen["error"]


def test_advertise_async_answer_reaches_the_caller(server):
    """An advertiseAsync callback's resolved value is the caller's response."""
    seen = roslibjs(server, "services.mjs", "async_answers")
    assert seen == {"ok": True, "value": {"success": True, "message": "switched on"}}


def test_call_with_timeout_fails_when_the_provider_is_silent(server):
    """callService's timeout argument makes a call to a silent provider fail after that time."""
    seen = roslibjs(server, "services.mjs", "timeout")
    assert seen["ok"] is False
    assert "did not answer within 0.3 s" in seen["error"]
    assert 250 <= seen["waited_ms"] < 3000


def test_request_with_wrong_field_type_fails_naming_the_field(server):
    """A request whose field has the wrong type fails at the caller, naming the field, and
    never reaches the provider."""
    seen = roslibjs(server, "services.mjs", "bad_request")
    assert seen["ok"] is False
    assert "args.data must be a boolean" in seen["error"]
    assert seen["requests"] == []


def test_invalid_response_fails_the_call_naming_the_field(server):
    """A provider's response with a wrong field type fails the call, naming the field."""
    seen = roslibjs(server, "services.mjs", "invalid_response")
    assert seen["ok"] is False
    assert "values.sum must be an integer" in seen["error"]


def test_provider_leaving_fails_a_waiting_call_at_once(server):
    """A call without a timeout fails at once, rather than hanging, when its provider leaves."""
    seen = roslibjs(server, "services.mjs", "provider_leaves")
    assert seen["ok"] is False
    assert "/flaky went away" in seen["error"]
    assert seen["waited_ms"] < 3000


def test_call_to_a_nonexistent_service_fails(server):
    """A call to a service nobody provides reaches the failedCallback, naming the service."""
    seen = roslibjs(server, "services.mjs", "nonexistent")
    assert seen["ok"] is False
    assert "/no_such_service" in seen["error"]


def test_call_to_a_protected_service_answers_an_empty_object(server):
    """A call on a /protected service succeeds with {} (the rosjs rule) and goes nowhere."""
    seen = roslibjs(server, "services.mjs", "protected")
    assert seen == {"ok": True, "value": {}}


# -- actions -----------------------------------------------------------------------------

FIB6 = [0, 1, 1, 2, 3, 5, 8]


def test_goal_gets_feedback_then_the_result(server):
    """A goal sent to a roslibjs-advertised Fibonacci action gets each feedback, in order,
    then the result, and the server saw the goal as sent."""
    seen = roslibjs(server, "actions.mjs", "succeed")
    assert seen["outcome"] == "result"
    assert seen["value"] == {"sequence": FIB6}
    assert seen["feedback"] == [{"sequence": FIB6[:n]} for n in range(2, 8)]
    assert [(e["event"], e["goal"]) for e in seen["server"]] == [("goal", {"order": 6})]


def test_cancel_goal_reaches_the_server_and_the_client_hears_canceled(server):
    """Action.cancelGoal reaches the server's cancel callback for that goal, and its
    setCanceled reaches the client's failedCallback as canceled, with the partial result."""
    seen = roslibjs(server, "actions.mjs", "cancel")
    goal, cancel = seen["server"]
    assert (goal["event"], cancel["event"]) == ("goal", "cancel")
    assert cancel["id"] == goal["id"]
    assert seen["feedback"] == [{"sequence": [0, 1]}]
    assert seen["outcome"] == "failed"
    assert seen["value"].startswith("GoalError: Action was canceled")
    assert '{"sequence":[0,1]}' in seen["value"]


def test_cancel_all_goals_cancels_every_goal_of_the_action(server):
    """Action.cancelAllGoals (a call of <action>/_action/cancel_goal with a zero goal id)
    reaches the server's cancel callback for every running goal, whoever sent it, and each
    client hears its goal canceled."""
    seen = roslibjs(server, "actions.mjs", "cancel_all")
    events = [(e["event"], e["id"]) for e in seen["server"]]
    goals = {i for event, i in events if event == "goal"}
    assert len(goals) == 2
    assert {i for event, i in events if event == "cancel"} == goals
    for result in seen["results"]:
        assert result["outcome"] == "failed"
        assert result["value"].startswith("GoalError: Action was canceled")


def test_cancel_all_goals_cancels_a_goal_the_lab_serves(server):
    """cancelAllGoals also cancels a goal of an action served inside the lab (here with
    action_tutorials_interfaces' Fibonacci, as the ROS 2 tutorials' server)."""
    served: list[Any] = []

    def serve(goal: Any) -> None:
        served.append(goal)
        goal.feedback({"partial_sequence": [0, 1]})  # then runs until cancelled

    graph = server.lab.graphs["playground"]
    server.call(
        lambda: graph.create_node("/fibonacci_server").provide_action(
            "/lab_fibonacci", "action_tutorials_interfaces/action/Fibonacci", serve
        )
    )
    seen = roslibjs(server, "actions.mjs", "cancel_all_lab")
    assert seen["feedback"] == [{"partial_sequence": [0, 1]}]
    assert seen["outcome"] == "failed"
    assert seen["value"].startswith("GoalError: Action was canceled")
    assert server.call(lambda: [g.status for g in served]) == [5]  # CANCELED


def test_client_leaving_cancels_its_goal_at_the_server(server):
    """When a roslibjs client closes its connection mid-goal, the server's cancel callback
    runs for that goal."""
    seen = roslibjs(server, "actions.mjs", "client_leaves")
    goal, cancel = seen["server"]
    assert (goal["event"], cancel["event"]) == ("goal", "cancel")
    assert cancel["id"] == goal["id"]


def test_set_failed_reaches_the_failed_callback_as_aborted(server):
    """Action.setFailed on the server side reaches the client's failedCallback as aborted."""
    seen = roslibjs(server, "actions.mjs", "fail")
    assert seen["outcome"] == "failed"
    assert seen["value"].startswith("GoalError: Action was aborted")
    assert seen["feedback"] == []


def test_goal_to_a_missing_action_fails(server):
    """A goal to an action nobody serves reaches the failedCallback, naming the action."""
    seen = roslibjs(server, "actions.mjs", "missing")
    assert seen["outcome"] == "failed"
    assert "/no_such_action" in seen["value"]


# -- rosapi ------------------------------------------------------------------------------


@pytest.fixture
def lab_node(server):
    """A node of the lab's own publishing one visible and one protected topic."""
    graph = server.lab.graphs["playground"]

    def make() -> Any:
        node = graph.create_node("/python_probe")
        node.advertise("/lab_visible", "std_msgs/msg/String")
        node.advertise("/protected/secret", "std_msgs/msg/String")
        return node

    return server.call(make)


def test_rosapi_topics_list_published_topics_with_types(server, lab_node):
    """getTopics lists roslibjs' and the lab's topics with their full type names, and hides
    protected ones; getTopicType and getTopicsForType agree."""
    seen = roslibjs(server, "rosapi.mjs", "graph")
    topics = dict(zip(seen["topics"]["topics"], seen["topics"]["types"], strict=True))
    assert topics["/rosapi_probe"] == "geometry_msgs/msg/Twist"
    assert topics["/lab_visible"] == "std_msgs/msg/String"
    assert "/protected/secret" not in topics
    assert seen["topic_type"] == "geometry_msgs/msg/Twist"
    assert seen["unknown_topic_type"] == ""
    assert seen["topics_for_type"] == ["/rosapi_probe"]
    raw = dict(
        zip(
            seen["topics_and_raw_types"]["topics"],
            seen["topics_and_raw_types"]["typedefs_full_text"],
            strict=True,
        )
    )
    assert "Vector3 linear" in raw["/rosapi_probe"]


def test_rosapi_services_nodes_and_action_servers(server, lab_node):
    """getServices, getServiceType, getNodes, getNodeDetails and getActionServers describe the
    graph that roslibjs clients and the lab built."""
    seen = roslibjs(server, "rosapi.mjs", "graph")
    assert {"/rosapi/topics", "/rosapi/get_param", "/probe_service"} <= set(seen["services"])
    assert seen["services_for_type"] == ["/probe_service"]
    assert seen["service_type"] == "rosapi_msgs/srv/Topics"
    assert seen["probe_service_type"] == "std_srvs/srv/Trigger"
    assert {"/rosapi", "/python_probe"} <= set(seen["nodes"])
    (publisher,) = seen["publishers"]
    assert publisher in seen["nodes"]
    assert seen["publisher_details"] == {
        "subscribing": [],
        "publishing": ["/rosapi_probe"],
        # with its action's cancel service, as a ROS 2 action server has
        "services": ["/fib_probe/_action/cancel_goal", "/probe_service"],
    }
    assert seen["action_servers"] == ["/fib_probe"]


def test_rosapi_message_details_decode_to_the_twist_layout(server):
    """getMessageDetails of geometry_msgs/Twist gives typedefs that roslibjs' decodeTypeDefs
    turns into the Twist layout; service request/response details describe AddTwoInts."""
    seen = roslibjs(server, "rosapi.mjs", "graph")
    vector = {"x": "float64", "y": "float64", "z": "float64"}
    assert seen["decoded"] == {"linear": vector, "angular": vector}
    assert [d["type"] for d in seen["message_details"]] == [
        "geometry_msgs/msg/Twist",
        "geometry_msgs/msg/Vector3",
    ]
    (request,) = seen["request_details"]["typedefs"]
    assert (request["fieldnames"], request["fieldtypes"]) == (["a", "b"], ["int64", "int64"])
    (response,) = seen["response_details"]["typedefs"]
    assert (response["fieldnames"], response["fieldtypes"]) == (["sum"], ["int64"])


def test_param_set_then_get_round_trips_json_values(server):
    """Param.set from one connection is what Param.get returns on another (and what the lab
    stores); unset and deleted parameters read as null."""
    seen = roslibjs(server, "rosapi.mjs", "params")
    assert seen["read"] == seen["written"]
    assert seen["number"] == 3
    assert seen["unset"] is None
    assert seen["deleted"] is None
    assert {"/max_speed", "/retries"} <= set(seen["names"])
    params = server.call(lambda: dict(server.lab.graphs["playground"].params))
    assert json.loads(params["/max_speed"]) == seen["written"]
    assert "/retries" not in params
