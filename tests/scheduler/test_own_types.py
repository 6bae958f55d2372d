"""A controller repository's own interface types: registered for its trial alone, published,
and recorded with their schemas; malformed ones end the trial before it starts."""

from __future__ import annotations

import asyncio
import json
import shutil
from pathlib import Path

import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from rosbags.highlevel import AnyReader

from labd.errors import UnknownTypeError
from labd.graph.graph import Side
from labd.recorder import read_channels
from labd.replay import replay
from repository.trial import Order, Outcome
from scheduler.controller import load
from scheduler.runner import run_trial
from tests.helpers.sandboxes import make_backend

pytestmark = pytest.mark.integration
OWN_TYPES = Path(__file__).resolve().parent / "controllers" / "own-types"


def run(backend, cache, host, tmp_path, source):
    out = tmp_path / f"run-{len(list(tmp_path.glob('run-*')))}"
    order = Order(repository=str(source), seed=2)
    return asyncio.run(run_trial(order, backend=backend, host=host, out=out, cache=cache))


def repository(tmp_path):
    folder = tmp_path / "own-types"
    shutil.copytree(OWN_TYPES, folder)
    folder.chmod(0o755)
    return folder


def test_own_debug_type_is_published_and_recorded_with_its_schema(backend, cache, host, tmp_path):
    """A controller publishes its own planner_msgs/msg/Debug: rosapi knows the type in its
    trial, the record holds the messages with the full schema (rosbags and the mcap decoder
    read them), the manifest digests the definitions, and the lab's own types stay as
    they were."""
    folder = repository(tmp_path)
    result = run(backend, cache, host, tmp_path, folder)
    assert result.outcome is Outcome.FAIL, result.reason  # three ticks, no goal: it ran
    assert result.metrics["ticks"] == 3
    seen = json.loads((result.folder / "controller.stdout.log").read_text())
    debug, *nested = seen["typedefs"]
    assert debug["type"] == "planner_msgs/msg/Debug"
    assert debug["fieldnames"] == ["phase", "cost", "path", "last"]
    assert {d["type"] for d in nested} == {"geometry_msgs/msg/Point", "planner_msgs/msg/Step"}

    (channel,) = [c for c in read_channels(result.folder) if c.topic == "/planner/debug"]
    assert channel.side is Side.CLIENT
    with result.mcap.open("rb") as stream:
        reader = make_reader(stream, decoder_factories=[DecoderFactory()])
        decoded = [
            (schema, message)
            for schema, channel, _, message in reader.iter_decoded_messages(
                topics=["/planner/debug"]
            )
        ]
    schema = decoded[0][0]
    assert schema.name == "planner_msgs/msg/Debug" and schema.encoding == "ros2msg"
    text = schema.data.decode()
    assert "geometry_msgs/Point[] path" in text and "MSG: planner_msgs/Step" in text
    assert "uint8 KIND_MOVE=1" in text
    assert [(m.phase, m.cost, m.path[0].x, m.last.kind) for _, m in decoded] == [
        ("search", float(tick), float(tick), 1) for tick in range(3)
    ]
    with AnyReader([result.folder]) as bag:
        connections = [c for c in bag.connections if c.topic == "/planner/debug"]
        costs = [bag.deserialize(raw, c.msgtype).cost for c, _, raw in bag.messages(connections)]
    assert costs == [0.0, 1.0, 2.0]

    controller = result.manifest.controller
    assert controller.interfaces == ("planner_msgs",)
    assert controller.interfaces_sha256 == load(folder).interfaces_sha256
    # a replay needs none of the controller's types: only the task's commands move the robot
    assert replay(result.mcap).verified
    with pytest.raises(UnknownTypeError):
        host.types.message("planner_msgs/msg/Debug")  # that trial's alone


@pytest.mark.parametrize(
    ("files", "words"),
    [
        (
            {"planner_msgs/msg/Step.msg": "uint8 KIND_MOVE=1\nstrin kind\n"},
            "planner_msgs/msg/Step.msg, line 2: kind has the type planner_msgs/strin",
        ),
        (
            {"planner_msgs/msg/Step.msg": "uint8 KIND_MOVE=one\n"},
            "planner_msgs/msg/Step.msg, line 1: the constant KIND_MOVE must be an integer"
            " (uint8), not 'one'",
        ),
        (
            {"planner_msgs/msg/Step.msg": "Waypoint next\n"},
            "planner_msgs/msg/Step.msg, line 1: next has the type planner_msgs/Waypoint",
        ),
        (
            {"std_msgs/msg/String.msg": "string data\nint32 extra\n"},
            "std_msgs/msg/String.msg: std_msgs is a package the lab already has",
        ),
    ],
)
def test_bad_definitions_end_the_trial_at_start_with_file_and_line(
    cache, host, tmp_path, files, words
):
    """A syntax error, a reference to an unknown type, or a redefinition of a standard type
    ends the trial before the controller starts, naming the file and line; no record."""
    folder = repository(tmp_path)
    for name, text in files.items():
        (folder / name).parent.mkdir(parents=True, exist_ok=True)
        (folder / name).write_text(text)
    if "std_msgs/msg/String.msg" in files:
        toml = folder / "lab.toml"
        toml.write_text(toml.read_text().replace('"planner_msgs"', '["planner_msgs", "std_msgs"]'))
    result = run(make_backend("bwrap", cache), cache, host, tmp_path, folder)
    assert result.outcome is Outcome.ERROR
    assert result.reason.startswith(f"the repository's interfaces: {words}"), result.reason
    assert result.mcap is None and result.exit_code is None
