"""A client's view of a graph under a namespace (a match's side): what it spells is
mapped under its prefix, the lab's time and services stay shared, the other side's
topics are out of its reach, and what it is told names things as it spells them."""

from __future__ import annotations

import pytest

from labd.errors import NameError_
from labd.graph.names import Namespace

HOME, AWAY = Namespace("/home"), Namespace("/away")
ARRAY = "std_msgs/msg/Float64MultiArray"


def test_names_map_in_and_out():
    assert HOME.inward("/player_0/action") == "/home/player_0/action"
    assert HOME.inward("score") == "/home/score"  # relative names are absolute first
    assert HOME.inward("/away/score") == "/home/away/score"  # never the other side's
    for shared in ("/clock", "/lab/step", "/lab/episode", "/rosapi/topics"):
        assert HOME.inward(shared) == shared and HOME.outward(shared) == shared
    assert HOME.inward("/clockwork") == "/home/clockwork"  # /clock is one name, not a prefix
    assert HOME.outward("/home/player_0/action") == "/player_0/action"
    assert HOME.outward("/away/score") is None and HOME.outward("/homework") is None
    with pytest.raises(NameError_):
        HOME.inward("/player 0")
    with pytest.raises(NameError_):
        Namespace("/home/")


def test_each_side_publishes_and_hears_its_own_topics_only(graph, connect):
    """Two clients on one graph, one a side each, say the same names: each reaches its
    own side's topics, the lab hears both apart, and neither hears the other's."""
    heard: dict[str, list[object]] = {"/home/player_0/action": [], "/away/player_0/action": []}
    lab = graph.create_node("/robot")
    for topic, messages in heard.items():
        lab.subscribe(topic, ARRAY, lambda message, kept=messages: kept.append(message))
    scores = {side: lab.advertise(f"/{side}/score", "std_msgs/msg/Int32MultiArray")
              for side in ("home", "away")}  # fmt: skip
    home, away = connect(namespace=HOME), connect(namespace=AWAY)
    home.send({"op": "set_level", "level": "info"})  # told of what it advertises
    for client in (home, away):
        client.send({"op": "subscribe", "topic": "/score"})
        client.send({"op": "subscribe", "topic": "/away/score"})  # /SIDE/away/score: nothing
    told = home.frames() + away.frames()
    assert [f for f in told if f["op"] != "status"] == []  # nothing published yet
    assert "/score" in str(told) and "/home" not in str(told) and "/away/score" in str(told)
    scores["home"].publish({"data": [1, 0]})
    scores["away"].publish({"data": [0, 1]})
    home_heard, away_heard = home.frames(), away.frames()
    assert [(f["topic"], f["msg"]["data"]) for f in home_heard] == [("/score", [1, 0])]
    assert [(f["topic"], f["msg"]["data"]) for f in away_heard] == [("/score", [0, 1])]

    home.send({"op": "advertise", "topic": "/player_0/action", "type": ARRAY})
    home.send({"op": "publish", "topic": "/player_0/action", "msg": {"data": [1.0, 0.0, 0.0]}})
    away.send({"op": "publish", "topic": "player_0/action", "msg": {"data": [0.0, 1.0, 0.0]}})
    assert [m.data["data"] for m in heard["/home/player_0/action"]] == [[1.0, 0.0, 0.0]]
    assert [m.data["data"] for m in heard["/away/player_0/action"]] == [[0.0, 1.0, 0.0]]
    said = [f["msg"] for f in home.frames() if f.get("op") == "status"]
    assert all("/home" not in text for text in said), said  # its side is not told


def test_the_lab_services_are_shared_and_errors_name_what_the_client_spelled(graph, connect):
    lab = graph.create_node("/robot")
    lab.provide_service(
        "/lab/step",
        "std_srvs/srv/Trigger",
        lambda call: call.reply({"success": True, "message": "tick"}),
    )
    home = connect(namespace=HOME)
    home.send({"op": "call_service", "service": "/lab/step", "id": "1"})
    answer = home.frames()[-1]
    assert answer["op"] == "service_response" and answer["result"] is True, answer
    home.send({"op": "call_service", "service": "/no_such", "id": "2"})
    refused = home.frames()
    text = str(refused)
    assert "/no_such" in text and "/home" not in text, refused
    home.send({"op": "set_level", "level": "info"})
    home.send({"op": "publish", "topic": "/nobody", "msg": {}, "id": "3"})
    text = str(home.frames())
    assert "/nobody" in text and "/home" not in text
