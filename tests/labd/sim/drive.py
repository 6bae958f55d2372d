"""Drive a task in lockstep with seeded random commands and digest everything it publishes.

Run as a program (``python -m tests.labd.sim.drive SEED TICKS TASK...``) it prints one
JSON object, each task's result by its name, so tests can compare what separate
processes produced.
"""

from __future__ import annotations

import copy
import hashlib
import json
import sys
from typing import Any

import numpy as np

from labd.graph.codec import Codec, codec_for
from labd.graph.graph import Graph
from labd.graph.types import FLOATS, Kind, TypeRegistry
from labd.sim.registry import TaskSpec
from labd.sim.robot import Robot


def random_value(
    codec: Codec, registry: TypeRegistry, rng: np.random.Generator, scale: float = 1.0
) -> dict[str, Any]:
    """A message with every float scalar (and fixed float array) drawn from [-scale, scale]."""
    out: dict[str, Any] = {}
    for field in codec.type.fields:
        if field.base in FLOATS and field.kind is Kind.SCALAR:
            out[field.name] = float(rng.uniform(-scale, scale))
        elif field.base in FLOATS and field.kind is Kind.ARRAY:
            out[field.name] = rng.uniform(-scale, scale, field.length).tolist()
        elif field.message and field.kind is Kind.SCALAR and "Time" not in field.message:
            inner = codec_for(registry, field.message)
            out[field.name] = random_value(inner, registry, rng, scale)
    return out


def random_command(
    spec: TaskSpec,
    topic: str,
    codec: Codec,
    registry: TypeRegistry,
    rng: np.random.Generator,
    scale: float = 1.0,
) -> dict[str, Any]:
    """``random_value``, except for a message whose numbers are a variable-length float
    array (a task's ``/action``): there its length is the task's action vector's
    (``TaskSpec.actions``), every value drawn from [-scale, scale] (not clipped)."""
    sequences = [f for f in codec.type.fields if f.base in FLOATS and f.kind is Kind.SEQUENCE]
    templates = spec.actions.templates if spec.actions is not None else {}
    if not sequences or topic not in templates:
        return random_value(codec, registry, rng, scale)
    message = copy.deepcopy(dict(templates[topic][1]))
    for field in sequences:
        message[field.name] = rng.uniform(-scale, scale, len(message[field.name])).tolist()
    return message


def drive(
    task: str, seed: int, ticks: int, params: dict[str, Any] | None = None, camera: bool = True
) -> dict[str, Any]:
    """Step ``task`` for ``ticks`` with random commands; digest every message published."""
    registry = TypeRegistry.default()
    graph = Graph(registry, name="drive")
    robot = Robot(graph, task, params or {}, seed)
    digest = hashlib.sha256()
    counts: dict[str, int] = {}
    listener = graph.create_node("/drive_listener")
    for obs in robot.sim.task.observations:
        if obs.on_demand and not camera:
            continue

        def take(message: Any, name: str = obs.name) -> None:
            digest.update(name.encode())
            digest.update(message.cdr())
            counts[name] = counts.get(name, 0) + 1

        listener.subscribe(obs.name, None, take)
    client = graph.create_node("/driver")
    publishers = {
        c.name: (client.advertise(c.name, c.type), graph.codec(c.type))
        for c in robot.sim.task.commands
    }
    rng = np.random.default_rng(seed)
    for _ in range(ticks):
        for topic, (pub, codec) in publishers.items():
            if rng.random() < 0.5:
                pub.publish(random_command(robot.sim.spec, topic, codec, registry, rng))
        answers: list[Any] = []
        client.call_service("/lab/step", None, answers.append)
        if not answers[0].response.data["success"]:
            break
    return {
        "digest": digest.hexdigest(),
        "counts": counts,
        "ticks": robot.sim.tick,
        "status": robot.sim.status,
        "model": robot.sim.model_digest(),
        "time_ns": robot.sim.time_ns,
    }


if __name__ == "__main__":
    seed, ticks, tasks = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3:]
    for task in tasks:  # a line each, as it is driven: a reader waits only for its task
        print(json.dumps({task: drive(task, seed, ticks)}), flush=True)
