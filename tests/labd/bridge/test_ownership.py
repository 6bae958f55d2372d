"""The robot's topics and the lab's services refuse clients, through the protocol core (strings)."""

from __future__ import annotations

import pytest

from labd.graph.graph import Side
from labd.sim.robot import Robot
from tests.labd.sim.pointmass import TASK

POINT = "geometry_msgs/msg/PointStamped"
FORGED = {"header": {"frame_id": "odom"}, "point": {"x": 42.0}}


def status_client(connect):
    client = connect()
    client.send({"op": "set_level", "level": "info"})
    client.frames()
    return client


def errors(frames):
    return [f["msg"] for f in frames if f["op"] == "status" and f["level"] == "error"]


@pytest.fixture
def robot(graph):
    made = Robot(graph, TASK, {}, seed=1)
    yield made
    made.close()


@pytest.fixture
def tapped(graph):
    """Every message delivered on the graph, with its topic and its publisher's side."""
    heard = []
    graph.taps.append(
        lambda topic, message, side, sender: heard.append((topic.name, side, message.data))
    )
    return heard


def test_advertising_a_robot_topic_is_refused_naming_it(connect, robot):
    """advertise /pose gets an error status naming the topic and why; no publisher is made."""
    client = status_client(connect)
    client.send({"op": "advertise", "topic": "/pose", "type": POINT, "id": "adv-1"})
    assert client.frames() == [
        {
            "op": "status",
            "level": "error",
            "msg": "advertise: topic /pose belongs to the lab (/robot publishes it); "
            "clients cannot advertise or publish on it",
            "id": "adv-1",
        }
    ]
    assert [p.node.name for p in robot.graph.topics["/pose"].publishers] == ["/robot"]


@pytest.mark.parametrize("topic", ["/pose", "pose", "/clock", "/lab/episode", "/slow"])
def test_publishing_without_advertising_is_refused_and_reaches_no_one(
    connect, robot, tapped, topic
):
    """A bare publish on a robot topic is refused; subscribers and taps never see it."""
    watcher, forger = connect(), status_client(connect)
    watcher.send({"op": "subscribe", "topic": topic})
    watcher.frames()  # the latched state
    tapped.clear()
    for _ in range(3):
        forger.send({"op": "publish", "topic": topic, "msg": {}})
    refusals = errors(forger.frames())
    assert len(refusals) == 3
    assert all(
        m.startswith(f"publish: topic /{topic.lstrip('/')} belongs to the lab") for m in refusals
    )
    assert watcher.frames() == []
    assert [(t, s) for t, s, _ in tapped] == [("/rosout", Side.LAB)] * 3  # the lab's log lines


def test_a_client_that_advertised_before_the_robot_is_cut_off(graph, connect, tapped):
    """The robot's claim revokes a client publisher made before it; the next publish is refused."""
    forger, watcher = status_client(connect), connect()
    forger.send({"op": "advertise", "topic": "/pose", "type": POINT})
    watcher.send({"op": "subscribe", "topic": "/pose", "type": POINT})
    forger.send({"op": "publish", "topic": "/pose", "msg": {"point": {"x": 1.0}}})
    robot = Robot(graph, TASK, {}, seed=1)
    try:
        forger.frames()
        tapped.clear()
        forger.send({"op": "publish", "topic": "/pose", "msg": FORGED})
        forger.send({"op": "advertise", "topic": "/pose", "type": POINT})
        assert [m.split(":")[0] for m in errors(forger.frames())] == ["publish", "advertise"]
        robot.step()
    finally:
        robot.close()
    xs = [f["msg"]["point"]["x"] for f in watcher.frames()]
    assert xs[0] == 1.0 and 42.0 not in xs and len(xs) == 3  # the client's, tick 0, tick 1
    assert all(side is Side.LAB for topic, side, _ in tapped if topic == "/pose")


def test_clients_publish_on_rosout_and_their_own_topics(connect, robot, tapped):
    """/rosout and topics the robot does not publish stay open to clients."""
    client = status_client(connect)
    client.send({"op": "advertise", "topic": "/rosout", "type": "rcl_interfaces/Log"})
    client.send({"op": "publish", "topic": "/rosout", "msg": {"msg": "hello"}})
    client.send({"op": "advertise", "topic": "/notes", "type": "std_msgs/String"})
    client.send({"op": "publish", "topic": "/notes", "msg": {"data": "mine"}})
    client.send({"op": "publish", "topic": "/cmd_vel", "msg": {"linear": {"x": 0.1}}})
    assert errors(client.frames()) == []
    assert [(t, s) for t, s, _ in tapped] == [
        ("/rosout", Side.CLIENT),
        ("/notes", Side.CLIENT),
        ("/cmd_vel", Side.CLIENT),
    ]


@pytest.mark.parametrize("live", [False, True], ids=["lockstep", "live"])
def test_no_lab_service_or_action_can_be_advertised(graph, connect, live):
    """Every service the lab provides, and /lab/step and /lab/reset, refuse a client provider."""
    robot = Robot(graph, TASK, {}, seed=1, live=live)
    try:
        lab_services = dict(graph.services)
        names = sorted({*lab_services, "/lab/step", "/lab/reset"})
        assert ("/lab/reset" if live else "/lab/step") in lab_services
        assert len([n for n in names if n.startswith("/rosapi/")]) > 20
        client = status_client(connect)
        for name in names:
            for spelling in (name, name.lstrip("/")):
                client.send(
                    {"op": "advertise_service", "service": spelling, "type": "std_srvs/Trigger"}
                )
                client.send(
                    {
                        "op": "advertise_action",
                        "action": spelling,
                        "type": "example_interfaces/Fibonacci",
                    }
                )
        refusals = errors(client.frames())
        assert len(refusals) == 4 * len(names)
        for refusal, name in zip(refusals[::4], names, strict=True):
            assert refusal.startswith(f"advertise_service: service {name} belongs to the lab")
        assert dict(graph.services) == lab_services
        assert not graph.actions
        if not live:
            client.send({"op": "call_service", "service": "/lab/step", "id": "s"})
            (answer,) = client.frames()
            assert answer["result"] is True and answer["values"]["message"].startswith("tick 1")
    finally:
        robot.close()
