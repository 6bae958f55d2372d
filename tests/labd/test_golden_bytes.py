"""The bytes the robot publishes do not change when the lab's encoding code does.

For every registered task, one short episode is stepped in-process with commands made
from a seeded generator (each task's command types, numbers within the robot's range),
and every message the lab publishes is taken as a record takes it: its topic, its
time, its CDR and its JSON. Their SHA-256 is compared with the one in
``tests/data/golden_bytes.json``, written by the code before the lab encoded CDR itself
and stopped validating its own messages (issue 21): a record made before still replays,
and a client still reads the same JSON.

A change that is meant to change these bytes is a new task version; then rewrite the
file with ``.venv/bin/python tests/labd/test_golden_bytes.py --write``, say why in the
commit, and keep the old version replayable.
"""

from __future__ import annotations

import hashlib
import json
import random
import sys
from pathlib import Path
from typing import Any

import pytest

from labd.graph.graph import Side
from labd.graph.types import TypeRegistry
from labd.sim import registry
from labd.station import Station

GOLDEN = Path(__file__).resolve().parents[1] / "data" / "golden_bytes.json"
TICKS = 25
SEED = 7


def command_for(type_name: str, topic: str, sim: Any, rng: random.Random) -> dict[str, Any] | None:
    """A command of ``type_name`` on ``topic`` with seeded numbers, or None to send none
    this tick."""
    if type_name == "geometry_msgs/msg/Twist":
        return {
            "linear": {"x": rng.uniform(-0.3, 0.5), "y": 0.0, "z": 0.0},
            "angular": {"x": 0.0, "y": 0.0, "z": rng.uniform(-1.5, 1.5)},
        }
    if type_name == "std_msgs/msg/Float64MultiArray":
        actions = sim.spec.actions  # as many values as the task's actions put there
        size = sum(dimension.topic == topic for dimension in actions.dimensions)
        if not size:  # not the task's actions (soccer's away side): it stands still
            return None
        return {"data": [rng.uniform(-1.0, 1.0) for _ in range(size)]}
    if type_name == "std_msgs/msg/Float64":
        return {"data": rng.uniform(0.0, 0.08)}
    return None  # trajectories and poses: the PR2 holds its arms


def episode_digest(types: TypeRegistry, task: str) -> str:
    """SHA-256 of the topic, time, CDR and JSON of everything the lab publishes."""
    station = Station(types, "golden", task, {}, SEED, live=False, protected_prefixes=())
    digest = hashlib.sha256()

    def tap(topic: Any, message: Any, side: Side, sender: Any) -> None:
        if side is Side.LAB:
            for part in (topic.name.encode(), str(message.stamp_ns).encode()):
                digest.update(part + b"\0")
            digest.update(message.cdr())
            digest.update(message.json())

    graph = station.graph
    graph.taps.append(tap)
    client = graph.create_node("/golden_client", side=Side.CLIENT)
    rng = random.Random(f"{task}:{SEED}")
    commands = station.robot.sim.task.commands
    publishers = {c.name: client.advertise(c.name, c.type) for c in commands}
    try:
        station.robot.publish()
        for _ in range(TICKS):
            if not station.robot.sim.running:
                break
            for command in commands:
                value = command_for(command.type, command.name, station.robot.sim, rng)
                if value is not None:
                    publishers[command.name].publish(value)
            station.robot.step()
    finally:
        graph.taps.remove(tap)
        station.close()
    return digest.hexdigest()


@pytest.mark.parametrize("task", sorted(registry.names()))
def test_published_bytes_are_unchanged(task: str) -> None:
    golden = json.loads(GOLDEN.read_text())
    assert task in golden, f"no golden bytes for {task}: run this file with --write"
    assert episode_digest(TypeRegistry.shared(), task) == golden[task], (
        f"what {task} publishes is no longer byte for byte what it was: its records no"
        " longer replay (see this file's docstring)"
    )


if __name__ == "__main__":
    if sys.argv[1:] != ["--write"]:
        raise SystemExit("usage: test_golden_bytes.py --write")
    types = TypeRegistry.shared()
    found = {name: episode_digest(types, name) for name in sorted(registry.names())}
    GOLDEN.write_text(json.dumps(found, indent=1, sort_keys=True) + "\n")
    print(f"wrote {len(found)} digests to {GOLDEN}")
