"""call_service, advertise_service and service_response through the protocol core."""

from __future__ import annotations

from labd.bridge.ops.services import Services
from labd.graph.services import simple_handler

ADD = "example_interfaces/srv/AddTwoInts"


def test_client_provided_service_is_called_by_another_client(connect):
    """A call is forwarded to the providing client and its answer returns to the caller."""
    provider, caller = connect(), connect()
    provider.send({"op": "advertise_service", "service": "/add", "type": ADD})
    caller.send({"op": "call_service", "id": "c1", "service": "add", "args": {"a": 2, "b": 3}})
    (request,) = provider.frames()
    assert request["op"] == "call_service" and request["service"] == "/add"
    assert request["args"] == {"a": 2, "b": 3}
    provider.send(
        {
            "op": "service_response",
            "id": request["id"],
            "service": "/add",
            "values": {"sum": 5},
            "result": True,
        }
    )
    assert caller.frames() == [
        {
            "op": "service_response",
            "service": "add",
            "values": {"sum": 5},
            "result": True,
            "id": "c1",
        }
    ]


def test_provider_failure_reaches_caller_as_result_false(connect):
    """result: false from the provider becomes result: false with its reason for the caller."""
    provider, caller = connect(), connect()
    provider.send({"op": "advertise_service", "service": "/add", "type": ADD})
    caller.send({"op": "call_service", "id": 7, "service": "/add", "args": {"a": 1, "b": 1}})
    (request,) = provider.frames()
    provider.send(
        {
            "op": "service_response",
            "id": request["id"],
            "service": "/add",
            "values": "overflow",
            "result": False,
        }
    )
    (reply,) = caller.frames()
    assert reply["result"] is False and reply["values"] == "overflow" and reply["id"] == 7


def test_invalid_response_fails_the_call_and_tells_the_provider(connect):
    """A response that does not fit its type fails the call and is reported to the provider."""
    provider, caller = connect(), connect()
    provider.send({"op": "set_level", "level": "error"})
    provider.send({"op": "advertise_service", "service": "/add", "type": ADD})
    provider.frames()
    caller.send({"op": "call_service", "service": "/add", "args": {"a": 1, "b": 1}})
    (request,) = provider.frames()
    provider.send(
        {
            "op": "service_response",
            "id": request["id"],
            "service": "/add",
            "values": {"sum": "two"},
            "result": True,
        }
    )
    (reply,) = caller.frames()
    assert reply["result"] is False and "values.sum must be an integer" in reply["values"]
    (status,) = provider.frames()
    assert status["op"] == "status" and "values.sum must be an integer" in status["msg"]


def test_call_times_out_after_the_default(connect, timers):
    """A call without a timeout fails after five seconds if the provider never answers."""
    provider, caller = connect(), connect()
    provider.send({"op": "advertise_service", "service": "/slow", "type": "std_srvs/srv/Trigger"})
    caller.send({"op": "call_service", "id": "t", "service": "/slow"})
    timers.advance(4.9)
    assert caller.frames() == []
    timers.advance(0.2)
    (reply,) = caller.frames()
    assert reply["result"] is False and "did not answer within 5 s" in reply["values"]
    # A late answer is dropped, not delivered twice.
    (request,) = provider.frames()
    provider.send(
        {
            "op": "service_response",
            "id": request["id"],
            "service": "/slow",
            "values": {"success": True, "message": ""},
            "result": True,
        }
    )
    assert caller.frames() == []


def test_explicit_timeout_and_no_timeout(connect, timers):
    """timeout: 1 gives up after a second; timeout: 0 waits for ever."""
    provider, caller = connect(), connect()
    provider.send({"op": "advertise_service", "service": "/slow", "type": "std_srvs/srv/Trigger"})
    caller.send({"op": "call_service", "id": "a", "service": "/slow", "timeout": 1})
    caller.send({"op": "call_service", "id": "b", "service": "/slow", "timeout": 0})
    timers.advance(1.5)
    assert [f["id"] for f in caller.frames()] == ["a"]
    timers.advance(3600)
    assert caller.frames() == []


def test_missing_service_and_bad_args_answer_result_false(connect):
    """Calls that cannot be made still get a service_response, so clients never hang."""
    caller = connect()
    caller.send({"op": "call_service", "id": 1, "service": "/nothing"})
    caller.send(
        {"op": "call_service", "id": 2, "service": "/rosapi/topic_type", "args": {"topic": 5}}
    )
    first, second = caller.frames()
    assert first["result"] is False and "no service /nothing" in first["values"]
    assert second["result"] is False and "args.topic must be a string" in second["values"]


def test_positional_args_fill_fields_in_order(connect, graph):
    """args may be a list, as rosbridge allows: it fills the request fields in order."""
    node = graph.create_node("/adder")
    node.provide_service("/add", ADD, simple_handler(lambda r: {"sum": r["a"] + r["b"]}))
    caller = connect()
    caller.send({"op": "call_service", "service": "/add", "args": [40, 2]})
    assert caller.frames()[0]["values"] == {"sum": 42}


def test_provider_leaving_fails_pending_calls_and_frees_the_name(connect):
    """When the providing client disconnects, its calls fail and the service disappears."""
    provider, caller = connect(), connect()
    provider.send({"op": "advertise_service", "service": "/add", "type": ADD})
    caller.send({"op": "call_service", "id": "x", "service": "/add", "args": {"a": 1, "b": 2}})
    provider.session.close()
    (reply,) = caller.frames()
    assert reply["result"] is False and "went away" in reply["values"]
    caller.send({"op": "call_service", "id": "y", "service": "/rosapi/services"})
    assert "/add" not in caller.frames()[0]["values"]["services"]


def test_second_provider_is_refused(connect):
    """A service name provided by one client cannot be taken over by another."""
    first, second = connect(), connect()
    second.send({"op": "set_level", "level": "error"})
    second.frames()
    first.send({"op": "advertise_service", "service": "/add", "type": ADD})
    second.send({"op": "advertise_service", "service": "/add", "type": ADD})
    (status,) = second.frames()
    assert "already provided by /bridge/client_1" in status["msg"]


def test_caller_leaving_abandons_its_calls(connect):
    """A caller that disconnects leaves no pending call behind at the provider's side."""
    provider, caller = connect(), connect()
    provider.send({"op": "advertise_service", "service": "/add", "type": ADD})
    caller.send({"op": "call_service", "service": "/add", "args": {"a": 1, "b": 2}})
    services = provider.session.capability(Services)
    assert len(services.incoming) == 1
    caller.session.close()
    assert services.incoming == {}
