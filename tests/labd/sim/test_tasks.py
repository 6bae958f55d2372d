"""The suite every registered task passes (as dm_control's suite_test does for its own).

Specs, parameters, topics that validate against their types, refused bad commands,
and determinism: the same task, parameters, seed and commands give bit-identical
observations in another process.
"""

from __future__ import annotations

import copy
import fcntl
import json
import math
import re
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from labd.errors import MessageError, OwnedError, ParamError, UnknownTaskError
from labd.graph.codec import codec_for
from labd.graph.graph import Graph, Side
from labd.graph.types import FLOATS, Kind
from labd.sim import registry
from labd.sim.base import stamp_of
from labd.sim.robot import Robot
from labd.sim.simulation import Simulation
from tests.labd.sim.drive import drive, random_command

ROOT = Path(__file__).resolve().parents[3]
TASKS = registry.names()
TICKS = 25
CAMERA = "/camera/image/compressed"


@pytest.fixture(scope="module", params=TASKS)
def task(request: pytest.FixtureRequest) -> str:
    return str(request.param)


@pytest.fixture(scope="module")
def sim(task: str) -> Simulation:
    return Simulation(task, {}, seed=1)


def test_unknown_task_lists_the_tasks():
    """Asking for a task that does not exist names the ones that do."""
    with pytest.raises(UnknownTaskError, match=r"the tasks are .*icreate-maze.*pr2-table"):
        registry.get("roomba-party")


def test_parameters_have_valid_defaults_and_refuse_the_unknown(task):
    """Defaults validate; an unknown or ill-typed parameter is refused with the valid list."""
    spec = registry.get(task)
    assert spec.params.validate({}) == spec.params.defaults()
    with pytest.raises(ParamError) as info:
        spec.params.validate({"no_such_parameter": 1})
    assert all(name in str(info.value) for name in spec.params.declared)
    first = next(iter(spec.params.declared.values()))
    wrong = "text" if first.kind is not str else 12345
    with pytest.raises(ParamError, match=first.name):
        spec.params.validate({first.name: wrong})


def test_specs_and_a_random_episode(task, sim):
    """The action spec is bounded and random actions within it step cleanly with finite rewards."""
    env = Simulation(task, {}, seed=2).env
    spec = env.action_spec()
    assert np.all(np.isfinite(spec.minimum)) and np.all(np.isfinite(spec.maximum))
    observation_spec = env.observation_spec()
    assert observation_spec
    rng = np.random.default_rng(0)
    timestep = env.reset()
    for _ in range(10):
        action = rng.uniform(spec.minimum, spec.maximum, spec.shape)
        timestep = env.step(action)
        assert math.isfinite(timestep.reward)
        assert set(timestep.observation) == set(observation_spec)


def _check_observation(observation: Any, spec: Any, tick: int) -> None:
    """As dm_control's suite_test does: the spec's keys, each array of its spec's shape
    and dtype, every value finite."""
    assert set(observation) == set(spec), (tick, sorted(observation), sorted(spec))
    for name, array_spec in spec.items():
        value = observation[name]
        assert isinstance(value, np.ndarray), (tick, name, type(value))
        assert (value.shape, value.dtype) == (array_spec.shape, array_spec.dtype), (tick, name)
        assert np.all(np.isfinite(value)), f"{name} at tick {tick} is not finite: {value}"


def test_an_episode_driven_by_commands_keeps_to_the_specs(task, registry):
    """Commands far past the robot's limits give actions within the action spec; every
    observation of the episode keeps its spec's keys, shapes and float64 dtype with finite
    values; rewards and discounts fit their specs and are finite."""
    sim = Simulation(task, {}, seed=3)
    env, lab_task = sim.env, sim.task
    observation_spec, action_spec = env.observation_spec(), env.action_spec()
    assert observation_spec
    assert {name: s.dtype for name, s in observation_spec.items()} == {
        name: np.float64 for name in observation_spec
    }
    codecs = [(c.name, codec_for(registry, c.type)) for c in lab_task.commands]
    rng = np.random.default_rng(3)
    timestep = env.reset()
    assert timestep.first() and timestep.reward is None
    _check_observation(timestep.observation, observation_spec, 0)
    for tick in range(1, TICKS + 1):
        for name, codec in codecs:  # each command, every field in [-5, 5]
            drawn = random_command(sim.spec, name, codec, registry, rng, 5.0)
            value = codec.normalize(drawn, lambda: (0, 0))
            lab_task.command(name, value)
        action = lab_task.action(sim.physics)
        action_spec.validate(action)  # its shape, dtype and bounds
        timestep = env.step(action)
        _check_observation(timestep.observation, observation_spec, tick)
        assert isinstance(timestep.reward, float) and math.isfinite(timestep.reward), tick
        env.reward_spec().validate(timestep.reward)
        env.discount_spec().validate(timestep.discount)
        assert timestep.mid(), f"the episode ended at tick {tick}"
    assert sum(lab_task.clipped.values()) >= TICKS // 2, lab_task.clipped  # bounds were tested


def test_topics_validate_against_their_types(task, sim, registry):
    """Every observation, cameras included, is a valid message of its declared type."""
    stamp = stamp_of(sim.physics)
    for obs in sim.task.observations:
        data = sim.task.observe(sim.physics, obs.name, stamp)
        assert data is not None, obs.name
        codec_for(registry, obs.type).normalize(data, lambda: (0, 0))
    for command in sim.task.commands:
        codec_for(registry, command.type)  # a known type


def _stamps(value: Any) -> list[Any]:
    """Every header stamp in a message, nested ones (each /tf transform's) included."""
    if isinstance(value, dict):
        own = [value["header"]["stamp"]] if "header" in value else []
        return own + [stamp for item in value.values() for stamp in _stamps(item)]
    if isinstance(value, list):
        return [stamp for item in value for stamp in _stamps(item)]
    return []


def _has_header(kind: str, registry: Any) -> bool:
    """Whether a message of type ``kind`` holds a std_msgs Header, at any depth."""
    fields = codec_for(registry, kind).type.fields
    return any(
        f.message is not None and ("Header" in f.message or _has_header(f.message, registry))
        for f in fields
    )


def test_observations_are_stamped_with_simulation_time(task, registry):
    """Every header the robot publishes, nested ones too, carries its tick's simulation time."""
    graph = Graph(registry, name="stamps")
    robot = Robot(graph, task, {}, seed=1)
    period_ns = round(robot.sim.control_timestep * 1e9)
    heard: list[tuple[int, str, Any]] = []  # (tick, topic, stamps)
    listener = graph.create_node("/listener")
    try:
        for obs in robot.sim.task.observations:  # at tick 0, as a controller subscribes
            listener.subscribe(
                obs.name,
                None,
                lambda m, name=obs.name: heard.append((robot.sim.tick, name, _stamps(m.data))),
            )
        for _ in range(3):
            robot.step()
    finally:
        robot.close()
    assert {topic for _, topic, _ in heard} == {o.name for o in robot.sim.task.observations}
    assert {tick for tick, _, _ in heard} == {0, 1, 2, 3}
    headed = {o.name for o in robot.sim.task.observations if _has_header(o.type, registry)}
    for tick, topic, stamps in heard:
        assert stamps or topic not in headed, f"{topic} at tick {tick} has no header"
        want = {"sec": tick * period_ns // 10**9, "nanosec": tick * period_ns % 10**9}
        assert all(stamp == want for stamp in stamps), (topic, tick, stamps)


def _nan_message(
    codec: Any, registry: Any, template: Any = None
) -> tuple[dict[str, Any], list[str]] | None:
    """The default message (or ``template``, a task's action message) with its first
    float set to NaN, and that field's path (``data[0]`` for a float array)."""
    value = codec.default() if template is None else copy.deepcopy(dict(template))
    for field in codec.type.fields:
        if field.base in FLOATS and field.kind is Kind.SCALAR:
            value[field.name] = math.nan
            return value, [field.name]
        if field.base in FLOATS and field.kind is not Kind.SCALAR and value[field.name]:
            value[field.name] = [math.nan, *list(value[field.name])[1:]]
            return value, [f"{field.name}[0]"]
        if field.message and field.kind is Kind.SCALAR:
            inner = _nan_message(codec_for(registry, field.message), registry)
            if inner is not None:
                value[field.name] = inner[0]
                return value, [field.name, *inner[1]]
    return None


def test_nan_commands_are_refused_naming_the_field(task, registry):
    """A NaN in any command is refused with an error that names the field."""
    sim = Simulation(task, {}, seed=1)
    checked = 0
    for command in sim.task.commands:
        templates = sim.spec.actions.templates if sim.spec.actions is not None else {}
        template = templates.get(command.name, (None, None))[1]
        found = _nan_message(codec_for(registry, command.type), registry, template)
        if found is None:
            continue
        value, path = found
        with pytest.raises(MessageError) as info:
            sim.task.command(command.name, value)
        assert ".".join(path) in str(info.value), command.name
        checked += 1
    assert checked, "no command with a float field to check"


# sh -c: run "$4"... with its output to "$1" and errors to "$2", then its status to "$3"
SH_STATUS = 'out=$1 err=$2 rc=$3; shift 3; "$@" >"$out" 2>"$err"; echo $? >"$rc"'


@pytest.fixture(scope="session")
def elsewhere(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Callable[[str], Any]]:
    """Every task driven in one other process (one import of the simulator for all), once
    for a whole parallel run: the first worker to ask starts it, and every worker reads a
    task's line from its output as soon as it is written (it drives the tasks in order)."""
    shared = tmp_path_factory.getbasetemp().parent  # the same folder for every worker
    kept, status, errors = (shared / f"tasks-driven-elsewhere.{x}" for x in ("jsonl", "rc", "err"))
    other: subprocess.Popen[bytes] | None = None
    with open(shared / "tasks-driven-elsewhere.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not kept.exists():
            kept.touch()
            command = [sys.executable, "-m", "tests.labd.sim.drive", "5", str(TICKS), *TASKS]
            # its exit status goes to a file, for the workers that did not start it
            other = subprocess.Popen(
                ["sh", "-c", SH_STATUS, "sh", kept, errors, status, *command],
                cwd=ROOT,
            )

    def driven(task: str) -> Any:
        deadline = time.monotonic() + 600
        while time.monotonic() < deadline:
            ended = status.exists()  # before reading: then every line it wrote is there
            for line in kept.read_text().splitlines(keepends=True):
                if line.endswith("\n") and task in (found := json.loads(line)):
                    return found[task]
            if ended:
                said = errors.read_text()[-2000:]
                pytest.fail(f"the other process ended ({status.read_text().strip()}): {said}")
            time.sleep(0.05)
        pytest.fail(f"the other process did not drive {task} in 600 s")

    yield driven
    if other is not None:
        other.wait(timeout=600)


def test_same_inputs_same_data_across_processes(task, elsewhere):
    """Another process given the same task, seed and commands publishes identical bytes."""
    here = drive(task, 5, TICKS)
    assert elsewhere(task) == here
    camera = next(o for o in registry.get(task).task_class.observations if o.name == CAMERA)
    assert here["counts"].get(CAMERA, 0) >= TICKS // max(1, camera.period) // 2


def test_different_seeds_differ(task):
    """Another seed gives other data (the seed reaches the task)."""
    assert drive(task, 5, 3, camera=False)["digest"] != drive(task, 6, 3, camera=False)["digest"]


def test_model_is_a_function_of_the_seed(task):
    """The compiled model is the same for the same seed and parameters."""
    assert (
        Simulation(task, {}, seed=9).model_digest() == Simulation(task, {}, seed=9).model_digest()
    )
    assert Simulation(task, {}, seed=9).model_xml


def test_every_topic_the_robot_publishes_is_the_labs(task, registry):
    """Observations (cameras included), /clock and /lab/episode are the lab's; commands are open."""
    graph = Graph(registry, name="ownership")
    robot = Robot(graph, task, {}, seed=1)
    try:
        published = {o.name for o in robot.sim.task.observations} | {"/clock", "/lab/episode"}
        assert set(robot.publishers) == published
        assert {n for n, t in graph.topics.items() if t.owner is robot.node} == published
        client = graph.create_node("/bridge/client_1", side=Side.CLIENT)
        for name in sorted(published):
            with pytest.raises(OwnedError, match=name):
                client.advertise(name, None)
        for command in robot.sim.task.commands:
            client.advertise(command.name, command.type)
    finally:
        robot.close()


def _documented_topics(task: str, section: str) -> set[str]:
    """The topics in the first column of a task's table in docs/tasks.md."""
    text = (ROOT / "docs" / "tasks.md").read_text()
    task_part = re.split(r"^## ", text, flags=re.M)
    (body,) = [p for p in task_part if p.startswith(f"`{task}`")]
    (table,) = [p for p in re.split(r"^### ", body, flags=re.M) if p.startswith(section)]
    rows = [line.split("|")[1] for line in table.splitlines() if line.startswith("| `/")]
    return {name for row in rows for name in re.findall(r"`(/[^`]*)`", row)}


def test_docs_list_the_tasks_topics(task, sim):
    """docs/tasks.md names each task's observation (lab-owned) and command topics exactly."""
    spec = registry.get(task)
    assert _documented_topics(spec.name, "Observations") == {o.name for o in sim.task.observations}
    assert _documented_topics(spec.name, "Commands") == {c.name for c in sim.task.commands}


def test_the_largest_seed_builds_an_episode(task):
    """Every task takes every seed a suite may draw (held-out seeds are 63-bit): the
    largest builds an episode that steps."""
    largest = Simulation(task, {}, seed=2**63 - 1)
    largest.step()
    assert (largest.seed, largest.tick) == (2**63 - 1, 1)
