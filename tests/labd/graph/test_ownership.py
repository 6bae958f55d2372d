"""Whose names: the lab's topics, services and actions refuse client nodes (the graph's rule)."""

from __future__ import annotations

import pytest

from labd.errors import ConflictError, OwnedError
from labd.graph.graph import Graph, Side

ODOM = "nav_msgs/msg/Odometry"
STRING = "std_msgs/msg/String"
TRIGGER = "std_srvs/srv/Trigger"
FIB = "example_interfaces/action/Fibonacci"


@pytest.fixture
def world(registry):
    graph = Graph(registry, name="ownership")
    robot = graph.create_node("/robot")
    client = graph.create_node("/bridge/client_1", side=Side.CLIENT)
    return graph, robot, client


def test_a_client_cannot_advertise_a_topic_the_lab_owns(world):
    """Advertising a lab-owned topic is an OwnedError naming the topic and its publisher."""
    graph, robot, client = world
    robot.advertise("/odom", ODOM, own=True)
    with pytest.raises(OwnedError) as info:
        client.advertise("odom", ODOM)
    assert info.value.name == "/odom" and info.value.owner == "/robot"
    assert str(info.value) == (
        "topic /odom belongs to the lab (/robot publishes it); "
        "clients cannot advertise or publish on it"
    )
    assert [p.node for p in graph.topics["/odom"].publishers] == [robot]
    assert client.publishers == []


def test_a_claim_revokes_publishers_clients_made_before(world):
    """A client publisher made before the lab claimed the topic is taken back: nothing passes."""
    graph, robot, client = world
    heard = []
    graph.create_node("/listener").subscribe("/odom", ODOM, lambda m: heard.append(m.data))
    early = client.advertise("/odom", ODOM)
    early.publish({"pose": {"pose": {"position": {"x": 1.0}}}})
    robot.advertise("/odom", ODOM, own=True).publish({})
    with pytest.raises(OwnedError, match="/odom belongs to the lab"):
        early.publish({"pose": {"pose": {"position": {"x": 42.0}}}})
    assert [m["pose"]["pose"]["position"]["x"] for m in heard] == [1.0, 0.0]
    assert early.closed and client.publishers == []
    with pytest.raises(OwnedError):
        client.advertise("/odom", ODOM)


def test_a_claim_holds_when_it_revokes_the_topics_only_other_user(world):
    """A topic whose sole user was a revoked client publisher stays the lab's."""
    graph, robot, client = world
    early = client.advertise("/odom", ODOM)
    robot.advertise("/odom", ODOM, own=True)
    assert early.closed and graph.topics["/odom"].owner is robot
    with pytest.raises(OwnedError):
        client.advertise("/odom", ODOM)


def test_lab_nodes_share_owned_topics_and_ownership_ends_with_the_owner(world):
    """Other lab nodes may publish an owned topic; once the owner stops, clients may again."""
    graph, robot, client = world
    owned = robot.advertise("/tf", "tf2_msgs/msg/TFMessage", own=True)
    graph.create_node("/tf_helper").advertise("/tf", "tf2_msgs/msg/TFMessage").publish({})
    owned.close()
    assert graph.topics["/tf"].owner is None
    client.advertise("/tf", "tf2_msgs/msg/TFMessage").publish({})


def test_only_lab_nodes_own_topics(world):
    """Asking to own a topic from a client's node is a bug in the lab: ValueError."""
    _, _, client = world
    with pytest.raises(ValueError, match="only the lab owns topics"):
        client.advertise("/odom", ODOM, own=True)


def test_rosout_stays_shared(world):
    """Clients publish their log lines on /rosout beside the lab's."""
    graph, _, client = world
    graph.rosout(20, "labd", "the lab speaks")
    client.advertise("/rosout", "rcl_interfaces/msg/Log").publish({"msg": "so does a client"})


@pytest.mark.parametrize("name", ["/lab/episode", "/lab/anything", "/rosapi/topics"])
def test_the_labs_namespaces_refuse_client_topics(world, name):
    """Topics under /lab/ and /rosapi/ are the lab's even before anyone publishes them."""
    graph, _, client = world
    with pytest.raises(OwnedError, match=f"every name under /{name.split('/')[1]}/"):
        client.advertise(name, STRING)
    assert name not in graph.topics


def test_taps_hear_the_publishers_side(world):
    """A tap learns, with each message, whether the lab or a client published it."""
    graph, robot, client = world
    heard = []
    graph.taps.append(lambda topic, message, side, sender: heard.append((topic.name, side)))
    robot.advertise("/odom", ODOM, own=True).publish({})
    client.advertise("/cmd_vel", "geometry_msgs/msg/Twist").publish({})
    assert heard == [("/odom", Side.LAB), ("/cmd_vel", Side.CLIENT)]


@pytest.mark.parametrize("name", ["/lab/step", "/lab/reset", "/rosapi/nodes", "/lab/other"])
def test_clients_cannot_provide_services_in_the_labs_namespaces(world, name):
    """Services under /lab/ and /rosapi/ are refused to clients whether or not the lab has them."""
    graph, robot, client = world
    robot.provide_service("/lab/step", TRIGGER, lambda call: call.reply({}))
    with pytest.raises(OwnedError, match=f"service {name} belongs to the lab"):
        client.provide_service(name, TRIGGER, lambda call: call.reply({}))
    assert name not in graph.services or graph.services[name].node is robot


def test_clients_cannot_take_a_service_or_action_the_lab_provides(world):
    """Outside its namespaces, a lab-provided name is refused to clients, naming the provider."""
    graph, robot, client = world
    robot.provide_service("/reset_world", TRIGGER, lambda call: call.reply({}))
    robot.provide_action("/fib", FIB, lambda goal: None)
    with pytest.raises(OwnedError, match=r"service /reset_world belongs to the lab \(/robot"):
        client.provide_service("/reset_world", TRIGGER, lambda call: call.reply({}))
    with pytest.raises(OwnedError, match=r"action /fib belongs to the lab \(/robot provides"):
        client.provide_action("/fib", FIB, lambda goal: None)
    with pytest.raises(OwnedError, match="every name under /lab/"):
        client.provide_action("/lab/fib", FIB, lambda goal: None)
    assert graph.services["/reset_world"].node is robot and graph.actions["/fib"].node is robot


def test_clients_still_conflict_with_each_other(world):
    """Between two clients the first provider keeps the name, as before (ConflictError)."""
    graph, _, client = world
    other = graph.create_node("/bridge/client_2", side=Side.CLIENT)
    client.provide_service("/add", TRIGGER, lambda call: call.reply({}))
    with pytest.raises(ConflictError):
        other.provide_service("/add", TRIGGER, lambda call: call.reply({}))
