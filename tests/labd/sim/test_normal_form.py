"""Every task builds its observations in normal form, so the lab need not validate them.

The robot publishes what its task builds without passing it through ``normalize``
(``Publisher.publish_built``). That is safe only if what the task builds is exactly
what ``normalize`` would make of it: the same fields in the same order, each value of
the exact type (a ``float`` where the type says float64, never an ``int`` or a numpy
number; lists, not arrays; ``bytes`` for ``uint8[]``). Here every registered task runs
an episode with seeded commands, with its camera watched, and each message the robot
publishes is checked against its own normal form, type by type.
"""

from __future__ import annotations

import math
import random
from typing import Any

import pytest

from labd.graph.graph import Side
from labd.graph.types import TypeRegistry
from labd.sim import registry
from labd.station import Station
from tests.labd.test_golden_bytes import SEED, command_for

TICKS = 20


def difference(built: Any, normal: Any, path: str = "") -> str | None:
    """Where ``built`` is not exactly ``normal`` (types, key order, values), or None."""
    if type(built) is not type(normal):
        return f"{path or 'the message'}: {type(built).__name__}, normal form has" + (
            f" {type(normal).__name__}"
        )
    if isinstance(normal, dict):
        if list(built) != list(normal):
            return f"{path}: fields {list(built)}, normal form has {list(normal)}"
        for key in normal:
            found = difference(built[key], normal[key], f"{path}.{key}".lstrip("."))
            if found:
                return found
        return None
    if isinstance(normal, list):
        if len(built) != len(normal):
            return f"{path}: {len(built)} items, normal form has {len(normal)}"
        for i, (a, b) in enumerate(zip(built, normal, strict=True)):
            found = difference(a, b, f"{path}[{i}]")
            if found:
                return found
        return None
    if isinstance(normal, float) and math.isnan(normal) and math.isnan(built):
        return None
    return None if built == normal else f"{path}: {built!r}, normal form has {normal!r}"


def test_the_labs_own_tasks_claim_normal_form() -> None:
    """The maze, the PR2 and the dm_control pack publish unvalidated."""
    own = [n for n in registry.names() if registry.get(n).build.__module__.startswith("labd.")]
    assert len(own) >= 28
    assert [n for n in own if not registry.get(n).normal_form] == []


@pytest.mark.parametrize("task", sorted(registry.names()))
def test_observations_are_built_in_normal_form(task: str) -> None:
    if not registry.get(task).normal_form:
        pytest.skip("the robot validates this task's observations: it does not claim normal form")
    station = Station(
        TypeRegistry.shared(), "normal", task, {}, SEED, live=False, protected_prefixes=()
    )
    robot = station.robot
    checked: dict[str, int] = {}
    problems: list[str] = []

    def check(topic: Any, message: Any, side: Side, sender: Any) -> None:
        if sender is not robot.node:
            return
        normal = message.codec.normalize(message.data, lambda: (0, 0))
        found = difference(message.data, normal)
        if found and len(problems) < 1:
            problems.append(f"{topic.name} ({topic.type_name}) {found}")
        checked[topic.name] = checked.get(topic.name, 0) + 1

    graph = station.graph
    graph.taps.append(check)
    client = graph.create_node("/normal_client", side=Side.CLIENT)
    for camera in (o.name for o in robot.sim.task.observations if o.on_demand):
        client.subscribe(camera, None, lambda _message: None)
    rng = random.Random(f"{task}:{SEED}")
    commands = robot.sim.task.commands
    publishers = {c.name: client.advertise(c.name, c.type) for c in commands}
    try:
        robot.publish()
        for _ in range(TICKS):
            if not robot.sim.running:
                break
            for command in commands:
                value = command_for(command.type, command.name, robot.sim, rng)
                if value is not None:
                    publishers[command.name].publish(value)
            robot.step()
    finally:
        station.close()
    assert not problems, "\n".join(problems)
    observed = {o.name for o in robot.sim.task.observations} | {"/clock", "/lab/episode"}
    assert set(checked) == observed  # every topic was published and checked
