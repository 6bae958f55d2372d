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


# -- <action>/_action/cancel_goal (roslibjs' cancelAllGoals) -------------------------------


def cancel_goal(client, args, id_="c", others=None):
    """Call the action's cancel service; return its response values (and keep the other
    frames the client received meanwhile in ``others``)."""
    frame = {"op": "call_service", "service": "/fib/_action/cancel_goal", "args": args}
    client.send(frame if id_ is None else {**frame, "id": id_})
    frames = client.frames()
    (reply,) = [f for f in frames if f["op"] == "service_response"]
    assert reply["result"] is True, reply
    if others is not None:
        others += [f for f in frames if f is not reply]
    return reply["values"]


def test_cancel_all_goals_of_a_client_served_action(connect):
    """A zero goal id and stamp (what cancelAllGoals sends) cancel every client's goals."""
    server, alice, bob = connect(), connect(), connect()
    advertise(server)
    alice.send({"op": "send_action_goal", "id": "a", "action": "/fib", "args": {"order": 9}})
    bob.send({"op": "send_action_goal", "id": "b", "action": "/fib", "args": {"order": 9}})
    goals = server.frames()
    values = cancel_goal(alice, {}, id_=None)  # roslibjs sends no id
    assert values["return_code"] == 0  # ERROR_NONE
    assert len(values["goals_canceling"]) == 2
    uuids = {g["goal_id"]["uuid"] for g in values["goals_canceling"]}
    assert len(uuids) == 2 and "A" * 22 + "==" not in uuids  # none is the zero UUID
    cancels = server.frames()
    assert cancels == [{"op": "cancel_action_goal", "id": g["id"], "action": "/fib"} for g in goals]
    for goal in goals:
        server.send(
            {"op": "action_result", "id": goal["id"], "action": "/fib", "status": 5, "result": True}
        )
    assert [(f["id"], f["status"]) for f in alice.frames() + bob.frames()] == [
        ("a", 5),
        ("b", 5),
    ]


def test_cancel_by_stamp_by_id_and_unknown_ids(connect, graph, timers):
    """A stamp cancels the goals accepted at or before it, an id that goal alone; an id of a
    goal that ended is ERROR_GOAL_TERMINATED, one no goal had ERROR_UNKNOWN_GOAL_ID."""
    goals = []
    graph.create_node("/fibber").provide_action("/fib", FIB, goals.append)
    client = connect()
    for n in (1, 2, 3):
        client.send({"op": "send_action_goal", "id": n, "action": "/fib", "args": {"order": n}})
        timers.advance(1.0)  # accepted at 0 s, 1 s and 2 s of graph time
    ended: list = []
    by_time = cancel_goal(client, {"goal_info": {"stamp": {"sec": 1}}}, others=ended)
    assert [g["stamp"]["sec"] for g in by_time["goals_canceling"]] == [0, 1]
    assert [(f["id"], f["status"]) for f in ended] == [(1, 5), (2, 5)]  # no on_cancel: at once
    uuid = list(goals[2].info()["goal_id"]["uuid"])
    by_id = cancel_goal(client, {"goal_info": {"goal_id": {"uuid": uuid}}}, others=ended)
    assert [g["stamp"]["sec"] for g in by_id["goals_canceling"]] == [2]
    assert [(f["id"], f["status"]) for f in ended] == [(1, 5), (2, 5), (3, 5)]
    assert cancel_goal(client, {"goal_info": {"goal_id": {"uuid": uuid}}}) == {
        "return_code": 3,  # ERROR_GOAL_TERMINATED
        "goals_canceling": [],
    }
    assert cancel_goal(client, {"goal_info": {"goal_id": {"uuid": [7] * 16}}}) == {
        "return_code": 2,  # ERROR_UNKNOWN_GOAL_ID
        "goals_canceling": [],
    }


def test_cancel_with_no_goals_is_rejected_and_the_service_goes_with_its_action(connect):
    """With no goal in progress the answer is ERROR_REJECTED; unadvertising the action
    removes its cancel service."""
    server, client = connect(), connect()
    advertise(server)
    assert cancel_goal(client, {}) == {"return_code": 1, "goals_canceling": []}
    server.send({"op": "unadvertise_action", "action": "/fib"})
    client.send({"op": "call_service", "id": "x", "service": "/fib/_action/cancel_goal"})
    (reply,) = client.frames()
    assert reply["result"] is False and "no service" in reply["values"]
