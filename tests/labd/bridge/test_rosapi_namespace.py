"""rosapi answers a namespaced client from its own view: a real bridge serves one graph
to the home side, the away side and a client without a namespace; each side asks in its
own names, is answered in them, and learns nothing of the other side's."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator, Callable
from typing import Any

import orjson
import pytest
from websockets.asyncio.client import ClientConnection, connect
from websockets.typing import Subprotocol

from labd.bridge.rosapi_view import VIEWS, Kind, View
from labd.bridge.server import BridgeServer
from labd.config import BridgeConfig
from labd.graph.graph import Graph
from labd.graph.names import Namespace
from tests.helpers.timing import SECOND

pytestmark = pytest.mark.integration
WAIT = 10 * SECOND
ARRAY = "std_msgs/msg/Float64MultiArray"
SCORE = "std_msgs/msg/Int32MultiArray"
TRIGGER = "std_srvs/srv/Trigger"
SIDES = ("home", "away")

# A question for every rosapi service, naming things as a side spells its own.
QUESTIONS: dict[str, dict[str, Any]] = {
    "topics": {},
    "topics_for_type": {"type": ARRAY},
    "topic_type": {"topic": "/player_0/action"},
    "topics_and_raw_types": {},
    "services": {},
    "services_for_type": {"type": TRIGGER},
    "service_type": {"service": "/reset"},
    "service_providers": {"service": "/reset"},
    "service_node": {"service": "/reset"},
    "message_details": {"type": SCORE},
    "service_request_details": {"type": TRIGGER},
    "service_response_details": {"type": TRIGGER},
    "nodes": {},
    "node_details": {"node": "/coach"},
    "publishers": {"topic": "/score"},
    "subscribers": {"topic": "/player_0/action"},
    "action_servers": {},
    "get_param": {"name": "gain"},
    "set_param": {"name": "gain", "value": "1"},
    "has_param": {"name": "gain"},
    "delete_param": {"name": "nothing"},
    "get_param_names": {},
    "get_time": {},
    "get_ros_version": {},
}


class Client:
    """A raw rosbridge client: asks a service and waits for its answer."""

    def __init__(self, ws: ClientConnection) -> None:
        self.ws = ws
        self._ids = iter(range(1, 1_000_000))

    async def answer(self, service: str, args: Any = None) -> dict[str, Any]:
        """The whole service_response to one call."""
        call_id = f"call:{next(self._ids)}"
        frame = {"op": "call_service", "id": call_id, "service": service, "args": args or {}}
        await self.ws.send(orjson.dumps(frame).decode())
        async with asyncio.timeout(WAIT):
            while True:
                reply = orjson.loads(await self.ws.recv())
                if reply.get("op") == "service_response" and reply.get("id") == call_id:
                    return dict(reply)

    async def call(self, service: str, args: Any = None) -> Any:
        """The values of a call that must succeed."""
        reply = await self.answer(service, args)
        assert reply["result"] is True, reply
        return reply["values"]


@pytest.fixture
def match_graph(graph: Graph) -> Graph:
    """A match's graph: the lab's soccer node with both sides' topics, a coach node on
    each side with its own topic, service and action, and the lab's shared /clock and
    /lab/step."""
    lab = graph.create_node("/soccer")
    lab.advertise("/clock", "rosgraph_msgs/msg/Clock")
    lab.provide_service("/lab/step", TRIGGER, lambda call: call.reply({"success": True}))
    for side in SIDES:
        lab.advertise(f"/{side}/score", SCORE)
        lab.advertise(f"/{side}/player_0/observation/ball", ARRAY)
        lab.subscribe(f"/{side}/player_0/action", ARRAY, lambda message: None)
        coach = graph.create_node(f"/{side}/coach")
        coach.advertise(f"/{side}/tactics", "std_msgs/msg/String")
        coach.subscribe(f"/{side}/score", SCORE, lambda message: None)
        coach.provide_service(f"/{side}/reset", TRIGGER, lambda call: call.reply({}))
        coach.provide_action(
            f"/{side}/kick", "example_interfaces/action/Fibonacci", lambda goal: None
        )
    return graph


@pytest.fixture
async def clients(match_graph: Graph) -> AsyncIterator[Callable[[str], Any]]:
    """``await clients(NAME)``: a client of the real bridge that serves the match's graph
    as ``home`` and ``away`` (each side's namespace) and ``plain`` (the graph's names)."""
    bridge = BridgeServer(
        {"home": match_graph, "away": match_graph, "plain": match_graph},
        BridgeConfig(port=0),
        namespaces={side: Namespace(f"/{side}") for side in SIDES},
    )
    await bridge.start()
    opened: list[ClientConnection] = []

    async def open_client(name: str) -> Client:
        ws = await connect(bridge.url(name))
        opened.append(ws)
        return Client(ws)

    yield open_client
    for ws in opened:
        await ws.close()
    await bridge.close()


def test_every_rosapi_service_is_asked_here():
    """The questions below cover every rosapi service, so a new one is swept for leaks."""
    assert set(QUESTIONS) == set(VIEWS)


def test_a_list_in_step_goes_with_one_list_of_names():
    """A view whose in-step lists could be filtered by two lists of names is refused."""
    with pytest.raises(ValueError, match="in step"):
        View(tell={"a": Kind.NAMES, "b": Kind.NAMES}, along=("c",))


async def test_no_rosapi_service_tells_a_side_the_other_sides_names(clients):
    """Every rosapi service, asked by either side in its own names, answers without a
    word of either side's prefix: a side learns neither which it is nor the other's names."""
    for side in SIDES:
        client = await clients(side)
        for service, args in QUESTIONS.items():
            reply = await client.answer(f"/rosapi/{service}", args)
            assert reply["result"] is True, reply
            text = orjson.dumps(reply).decode()
            assert "home" not in text and "away" not in text, (side, service, text)


async def test_both_sides_of_a_symmetric_match_get_the_same_answers(clients):
    """Each side's half of the graph is the other's with the prefix changed, so every
    rosapi answer, lists in their order included, is the same for both: nothing in an
    answer tells a side which it is."""
    home, away = await clients("home"), await clients("away")
    for service, args in QUESTIONS.items():
        asked = f"/rosapi/{service}"
        assert await home.answer(asked, args) == await away.answer(asked, args), service


async def test_each_side_lists_its_own_names_unprefixed_and_the_shared_as_they_are(clients):
    """topics (with their types and type texts in step), services, actions and nodes list
    a side's own names without its prefix, the shared /clock, /lab/ and /rosapi/ as they
    are, and nothing of the other side or the lab's own nodes."""
    for side in SIDES:
        client = await clients(side)
        topics = await client.call("/rosapi/topics")
        assert dict(zip(topics["topics"], topics["types"], strict=True)) == {
            "/clock": "rosgraph_msgs/msg/Clock",
            "/score": SCORE,
            "/player_0/observation/ball": ARRAY,
            "/player_0/action": ARRAY,
            "/tactics": "std_msgs/msg/String",
        }
        raw = await client.call("rosapi/topics_and_raw_types")
        assert raw["topics"] == topics["topics"] and raw["types"] == topics["types"]
        score = raw["typedefs_full_text"][raw["topics"].index("/score")]
        assert "std_msgs/MultiArrayLayout" in score  # the texts stay in step with the topics
        assert await client.call("/rosapi/topics_for_type", {"type": ARRAY}) == {
            "topics": ["/player_0/action", "/player_0/observation/ball"]
        }
        services = (await client.call("/rosapi/services"))["services"]
        assert {"/reset", "/kick/_action/cancel_goal", "/lab/step", "/rosapi/nodes"} <= set(
            services
        )
        assert all(s.startswith(("/reset", "/kick/", "/lab/", "/rosapi/")) for s in services)
        assert await client.call("/rosapi/services_for_type", {"type": TRIGGER}) == {
            "services": ["/lab/step", "/reset"]
        }
        assert await client.call("/rosapi/action_servers") == {"action_servers": ["/kick"]}
        assert await client.call("/rosapi/nodes") == {"nodes": ["/coach"]}


async def test_a_side_asks_in_its_own_names_and_never_reaches_the_other_sides(clients):
    """Names in requests are the side's own: /score is its score, /coach its coach, and
    /away/score spelled by the home side is /home/away/score, which does not exist."""
    for side in SIDES:
        client = await clients(side)
        assert await client.call("/rosapi/topic_type", {"topic": "/player_0/action"}) == {
            "type": ARRAY
        }
        assert await client.call("/rosapi/topic_type", ["score"]) == {"type": SCORE}  # in order
        for other in ("/away/score", "/home/score"):
            assert await client.call("/rosapi/topic_type", {"topic": other}) == {"type": ""}
            assert await client.call("/rosapi/publishers", {"topic": other}) == {"publishers": []}
        assert await client.call("/rosapi/subscribers", {"topic": "/score"}) == {
            "subscribers": ["/coach"]  # the lab's /soccer is out of a side's view
        }
        assert await client.call("/rosapi/publishers", {"topic": "/tactics"}) == {
            "publishers": ["/coach"]
        }
        assert await client.call("/rosapi/node_details", {"node": "coach"}) == {
            "subscribing": ["/score"],
            "publishing": ["/tactics"],
            "services": ["/kick/_action/cancel_goal", "/reset"],
        }
        for node in ("/soccer", "/away/coach", "/home/coach", "/rosapi"):
            assert await client.call("/rosapi/node_details", {"node": node}) == {
                "subscribing": [],
                "publishing": [],
                "services": [],
            }
        assert await client.call("/rosapi/service_type", {"service": "reset"}) == {"type": TRIGGER}
        assert await client.call("/rosapi/service_node", {"service": "/reset"}) == {
            "node": "/coach"
        }
        assert await client.call("/rosapi/service_providers", {"service": "/reset"}) == {
            "providers": ["/coach"]
        }
        assert await client.call("/rosapi/service_node", {"service": "/lab/step"}) == {
            "node": ""  # shared, but provided by the lab's node, which it does not see
        }
        assert await client.call("/rosapi/service_type", {"service": "/away/reset"}) == {"type": ""}


async def test_each_side_keeps_its_own_parameters(clients):
    """A side's parameters live under its prefix: both sides set gain, each reads its own,
    lists only its own, and cannot read, test or delete the other side's or the graph's."""
    home, away, plain = await clients("home"), await clients("away"), await clients("plain")
    await plain.call("/rosapi/set_param", {"name": "secret", "value": '"plain"'})
    await home.call("/rosapi/set_param", {"name": "gain", "value": "1"})
    await away.call("/rosapi/set_param", {"name": "/gain", "value": "2"})
    assert await home.call("/rosapi/get_param", {"name": "/gain"}) == {"value": "1"}
    assert await away.call("/rosapi/get_param", {"name": "gain"}) == {"value": "2"}
    assert await home.call("/rosapi/get_param_names") == {"names": ["/gain"]}
    assert await plain.call("/rosapi/get_param_names") == {
        "names": ["/away/gain", "/home/gain", "secret"]
    }
    for name in ("secret", "/away/gain", "/home/gain"):
        assert await home.call("/rosapi/has_param", {"name": name}) == {"exists": False}
        assert await home.call("/rosapi/get_param", {"name": name}) == {"value": "null"}
    await home.call("/rosapi/delete_param", {"name": "/away/gain"})  # its own /home/away/gain
    assert await away.call("/rosapi/has_param", {"name": "gain"}) == {"exists": True}
    await home.call("/rosapi/delete_param", {"name": "gain"})
    assert await plain.call("/rosapi/get_param_names") == {"names": ["/away/gain", "secret"]}
    refused = await home.answer("/rosapi/set_param", {"name": "odd", "value": "not json"})
    assert refused["result"] is False and refused["values"] == "the value of /odd must be JSON text"


async def test_a_malformed_name_fails_the_call_as_the_client_spelled_it(clients):
    """A name that is not a name fails the call with a sentence naming it as spelled;
    a field of the wrong kind is refused by the type, as without a namespace."""
    home = await clients("home")
    reply = await home.answer("/rosapi/topic_type", {"topic": "/player 0"})
    assert reply["result"] is False and "/player 0" in reply["values"], reply
    assert "home" not in reply["values"]
    reply = await home.answer("/rosapi/get_param", {"name": 5})
    assert reply["result"] is False and "must be a string" in reply["values"], reply
    reply = await home.answer("/rosapi/topic_type", ["/score", "/clock"])
    assert reply["result"] is False and "items" in reply["values"], reply
    assert await home.call("/rosapi/topic_type", {"topic": ""}) == {"type": ""}


async def test_a_rosapi_service_without_a_view_is_refused_under_a_namespace(clients, match_graph):
    """A rosapi service the view table does not know is never answered from the whole
    graph to a side; a client without a namespace is answered as ever."""
    rosapi = match_graph.nodes["/rosapi"]
    rosapi.provide_service("/rosapi/extra", TRIGGER, lambda call: call.reply({"message": "x"}))
    reply = await (await clients("home")).answer("/rosapi/extra")
    assert reply["result"] is False, reply
    assert reply["values"] == "/rosapi/extra is not answered in a namespaced view of the graph"
    assert (await (await clients("plain")).call("/rosapi/extra"))["message"] == "x"


async def test_a_client_without_a_namespace_sees_the_whole_graph(clients):
    """The graph's own names, both sides' and the lab's nodes, as before namespaces."""
    plain = await clients("plain")
    topics = (await plain.call("/rosapi/topics"))["topics"]
    assert {"/home/score", "/away/score", "/clock", "/rosout"} <= set(topics)
    nodes = (await plain.call("/rosapi/nodes"))["nodes"]
    assert {"/soccer", "/home/coach", "/away/coach", "/rosapi", "/labd"} <= set(nodes)
    assert await plain.call("/rosapi/topic_type", {"topic": "/home/score"}) == {"type": SCORE}
    assert await plain.call("/rosapi/service_node", {"service": "/lab/step"}) == {"node": "/soccer"}
    assert await plain.call("/rosapi/action_servers") == {
        "action_servers": ["/away/kick", "/home/kick"]
    }


async def test_a_side_asking_for_foxglove_is_served_rosbridge_only(match_graph):
    """Foxglove's channels would list every topic of the graph, both sides' included: a
    client of a side that offers Foxglove's protocol is answered without it (rosbridge,
    whose rosapi keeps to its view); a client of the whole graph gets Foxglove's."""
    bridge = BridgeServer(
        {"home": match_graph, "plain": match_graph},
        BridgeConfig(port=0),
        namespaces={"home": Namespace("/home")},
    )
    await bridge.start()
    try:
        offer = [Subprotocol("foxglove.sdk.v1")]
        async with connect(bridge.url("home"), subprotocols=offer) as side:
            assert side.subprotocol is None
        async with connect(bridge.url("plain"), subprotocols=offer) as whole:
            assert whole.subprotocol == "foxglove.sdk.v1"
            assert orjson.loads(await whole.recv())["op"] == "serverInfo"
    finally:
        await bridge.close()
