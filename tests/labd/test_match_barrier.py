"""The shared tick of a match (``labd.match.StepBarrier``) on a real soccer station: a
step is answered only once every side has called, each side's commands wait for its
call and reach the graph home's first, a command sent while waiting counts for the next
tick, and what is not a side's, too much, or too late is refused in words."""

from __future__ import annotations

from typing import Any

import pytest

from labd.config import BridgeConfig
from labd.graph.graph import Side
from labd.graph.services import ServiceResult
from labd.graph.types import TypeRegistry
from labd.match import MAX_CALLS, MAX_HELD, StepBarrier
from labd.station import Station

ARRAY = "std_msgs/msg/Float64MultiArray"


class Said:
    """What the barrier tells a session (the one thing it asks of it)."""

    def __init__(self) -> None:
        self.lines: list[tuple[str, str]] = []

    def report(self, level: str, text: str, op_id: Any = None) -> None:
        self.lines.append((level, text))


@pytest.fixture
def match() -> Any:
    station = Station(
        TypeRegistry.default(),
        "trial",
        "soccer-1v1",
        {},
        2,
        live=False,
        protected_prefixes=BridgeConfig().protected_prefixes,
    )
    graph = station.graph
    teams = {
        side: graph.create_node(f"/{side}/team", side=Side.CLIENT) for side in ("home", "away")
    }
    sides = {node: side for side, node in teams.items()}
    commands = [c.name for c in station.robot.sim.task.commands]
    barrier = StepBarrier(station.robot, ("home", "away"), commands, sides.get)
    heard: list[str] = []
    graph.taps.append(lambda topic, message, side, sender: heard.append(topic.name))
    try:
        yield station, barrier, teams, heard
    finally:
        station.close()


def step(node: Any) -> list[ServiceResult]:
    answers: list[ServiceResult] = []
    node.call_service("/lab/step", None, answers.append)
    return answers


def send(barrier: StepBarrier, node: Any, side: str, value: list[float], said: Said) -> None:
    publisher = node.advertise(f"/{side}/player_0/action", ARRAY)
    message = node.graph.message(ARRAY, {"data": value})
    if not barrier.hold(side)(said, publisher, message, None):  # type: ignore[arg-type]
        publisher.publish(message)


def test_a_tick_waits_for_every_side_and_takes_home_first(match):
    station, barrier, teams, heard = match
    said = Said()
    send(barrier, teams["away"], "away", [1.0, 0.0, 0.0], said)
    send(barrier, teams["home"], "home", [0.5, 0.0, 0.0], said)
    assert "/home/player_0/action" not in heard  # held until the side steps
    assert barrier.owing() == ["home", "away"]
    away = step(teams["away"])
    assert away == [] and station.robot.sim.tick == 0
    assert barrier.owing() == ["home"]
    send(barrier, teams["away"], "away", [-1.0, 0.0, 0.0], said)  # for the next tick
    home = step(teams["home"])
    assert station.robot.sim.tick == 1
    assert [a.ok for a in home + away] == [True, True]
    assert home[0].response.data == away[0].response.data  # the same answer, together
    actions = [t for t in heard if t.endswith("/action")]
    assert actions == ["/home/player_0/action", "/away/player_0/action"]
    held = station.robot.sim.task.held  # what each player does now: home's, then away's
    assert held.reshape(-1)[[0, 3]].tolist() == [0.5, 1.0]  # not yet the away's -1
    step(teams["home"])
    step(teams["away"])
    actions = [t for t in heard if t.endswith("/action")]
    assert actions[2:] == ["/away/player_0/action"]  # sent while waiting: the next tick's
    assert said.lines == []


def test_whoever_is_not_a_side_or_calls_too_often_is_refused(match):
    station, barrier, teams, _ = match
    stranger = station.graph.create_node("/stranger", side=Side.CLIENT)
    [answer] = step(stranger)
    assert not answer.ok and "stepped by the match's teams only" in answer.error
    for _ in range(MAX_CALLS):
        assert step(teams["home"]) == []
    [refused] = step(teams["home"])
    assert not refused.ok and f"{MAX_CALLS} step calls are already waiting" in refused.error
    assert station.robot.sim.tick == 0
    for _ in range(MAX_CALLS):
        step(teams["away"])
    assert station.robot.sim.tick == MAX_CALLS  # each waiting call got its tick


def test_a_flood_of_commands_between_two_steps_is_cut_and_said(match):
    _, barrier, teams, heard = match
    said = Said()
    for n in range(MAX_HELD + 3):
        send(barrier, teams["home"], "home", [0.0, 0.0, n / 1000], said)
    assert (
        said.lines
        == [
            (
                "error",
                f"publish: at most {MAX_HELD} commands between two steps; this one was dropped",
            )
        ]
        * 3
    )
    step(teams["home"])
    step(teams["away"])
    assert sum(t == "/home/player_0/action" for t in heard) == MAX_HELD


def test_a_refused_command_is_told_to_its_session_at_the_tick(match):
    station, barrier, teams, _ = match
    said = Said()
    send(barrier, teams["home"], "home", [float("nan"), 0.0, 0.0], said)
    assert said.lines == []
    step(teams["home"])
    step(teams["away"])
    assert station.robot.sim.tick == 1
    assert len(said.lines) == 1 and said.lines[0][0] == "error", said.lines
    assert said.lines[0][1].startswith("publish: ")


def test_after_the_end_every_step_is_answered_that_it_is_over(match):
    station, barrier, teams, _ = match
    sim = station.robot.sim
    while sim.running:
        step(teams["home"])
        step(teams["away"])
    [late] = step(teams["away"])
    assert late.ok and late.response.data["success"] is False
    assert "ended" in late.response.data["message"]
