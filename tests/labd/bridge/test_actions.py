"""The action ops through the protocol core."""

from __future__ import annotations

from labd.graph.actions import SUCCEEDED

FIB = "example_interfaces/action/Fibonacci"


def advertise(server):
    server.send({"op": "advertise_action", "action": "/fib", "type": FIB})


def test_goal_feedback_and_result_between_clients(connect):
    """A goal goes to the advertising client; its feedback and result come back with the goal id."""
    server, client = connect(), connect()
    advertise(server)
    client.send(
        {
            "op": "send_action_goal",
            "id": "g1",
            "action": "/fib",
            "action_type": FIB,
            "args": {"order": 3},
            "feedback": True,
        }
    )
    (goal,) = server.frames()
    assert goal["op"] == "send_action_goal" and goal["args"] == {"order": 3}
    server.send(
        {
            "op": "action_feedback",
            "id": goal["id"],
            "action": "/fib",
            "values": {"sequence": [0, 1]},
        }
    )
    server.send(
        {
            "op": "action_result",
            "id": goal["id"],
            "action": "/fib",
            "values": {"sequence": [0, 1, 1]},
            "status": SUCCEEDED,
            "result": True,
        }
    )
    assert client.frames() == [
        {"op": "action_feedback", "id": "g1", "action": "/fib", "values": {"sequence": [0, 1]}},
        {
            "op": "action_result",
            "id": "g1",
            "action": "/fib",
            "values": {"sequence": [0, 1, 1]},
            "status": SUCCEEDED,
            "result": True,
        },
    ]


def test_no_feedback_unless_asked(connect):
    """Feedback frames go only to a client that sent feedback: true."""
    server, client = connect(), connect()
    advertise(server)
    client.send({"op": "send_action_goal", "id": "g", "action": "/fib", "args": {"order": 1}})
    (goal,) = server.frames()
    server.send(
        {"op": "action_feedback", "id": goal["id"], "action": "/fib", "values": {"sequence": [0]}}
    )
    assert client.frames() == []


def test_cancel_is_forwarded_and_ends_with_canceled(connect):
    """cancel_action_goal reaches the server as a cancel with its goal id; status 5 ends it."""
    server, client = connect(), connect()
    advertise(server)
    client.send({"op": "send_action_goal", "id": "g", "action": "/fib", "args": {"order": 9}})
    (goal,) = server.frames()
    client.send({"op": "cancel_action_goal", "id": "g", "action": "/fib"})
    (cancel,) = server.frames()
    assert cancel == {"op": "cancel_action_goal", "id": goal["id"], "action": "/fib"}
    server.send(
        {
            "op": "action_result",
            "id": goal["id"],
            "action": "/fib",
            "values": {},
            "status": 5,
            "result": True,
        }
    )
    (result,) = client.frames()
    assert result["status"] == 5 and result["result"] is True


def test_failed_goal_and_missing_action(connect):
    """A server's result: false and a goal for no action both end with result: false."""
    server, client = connect(), connect()
    advertise(server)
    client.send({"op": "send_action_goal", "id": "a", "action": "/fib", "args": {"order": 1}})
    (goal,) = server.frames()
    server.send(
        {"op": "action_result", "id": goal["id"], "action": "/fib", "status": 6, "result": False}
    )
    client.send({"op": "send_action_goal", "id": "b", "action": "/none", "args": {}})
    failed, missing = client.frames()
    assert failed["result"] is False and failed["status"] == 6
    assert missing["result"] is False and missing["status"] == 0
    assert "no action /none" in missing["values"]


def test_server_leaving_aborts_goals(connect):
    """Goals in progress end, aborted with a reason, when the serving client disconnects."""
    server, client = connect(), connect()
    advertise(server)
    client.send({"op": "send_action_goal", "id": "g", "action": "/fib", "args": {"order": 1}})
    server.session.close()
    (result,) = client.frames()
    assert result["result"] is False and result["status"] == 6 and "went away" in result["values"]


def test_client_leaving_cancels_its_goals(connect):
    """When the goal's client disconnects, the serving client is told to cancel the goal."""
    server, client = connect(), connect()
    advertise(server)
    client.send({"op": "send_action_goal", "id": "g", "action": "/fib", "args": {"order": 1}})
    (goal,) = server.frames()
    client.session.close()
    assert server.frames() == [{"op": "cancel_action_goal", "id": goal["id"], "action": "/fib"}]


def test_in_process_action_server(connect, graph):
    """An action served inside the lab answers bridge clients the same way."""

    def serve(goal):
        n = goal.goal.data["order"]
        seq = [0, 1][:n]
        while len(seq) < n:
            seq.append(seq[-1] + seq[-2])
        goal.feedback({"sequence": seq[:1]})
        goal.finish(SUCCEEDED, {"sequence": seq})

    graph.create_node("/fibber").provide_action("/fib", FIB, serve)
    client = connect()
    client.send(
        {
            "op": "send_action_goal",
            "id": 1,
            "action": "fib",
            "action_type": FIB,
            "args": {"order": 5},
            "feedback": True,
        }
    )
    feedback, result = client.frames()
    assert feedback["values"] == {"sequence": [0]}
    assert result["values"] == {"sequence": [0, 1, 1, 2, 3]} and result["action"] == "fib"
