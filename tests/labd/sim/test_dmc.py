"""The dm_control suite pack: every task is dm_control's own, tick for tick.

The same in-range actions, fed through ``/action`` and stepped as the lab steps, give
exactly the rewards and observations of ``dm_control.suite.load(domain, task,
task_kwargs={"random": seed})`` stepped with them; the static catalogue is the real
environment's; bad actions are refused or clipped; the threshold decides the outcome.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import re
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import mujoco
import numpy as np
import pytest
import simplejpeg
from dm_control import suite

from labd.errors import MessageError
from labd.graph.codec import codec_for
from labd.graph.graph import Graph
from labd.sim.base import stamp_of
from labd.sim.dmc import CATALOG, LAYOUTS, TASKS, Listing, SuiteTask, actions_of, layout
from labd.sim.dmc.task import ARRAY, OPTICAL_FRAME, model_of, random_for
from labd.sim.robot import Robot
from labd.sim.simulation import Simulation
from repository.trial import EpisodeStatus

ROOT = Path(__file__).resolve().parents[3]
PACK = {spec.name: spec for spec in TASKS}
NAMES = sorted(PACK)
SEEDS = (0, 11)
TICKS = 30
ROS_NAME = re.compile(r"/[A-Za-z][A-Za-z0-9_]*(/[A-Za-z][A-Za-z0-9_]*)*")
# one task per domain: rendering needs a GL context per model, the costly part
NOW = lambda: (0, 0)  # noqa: E731  (a codec's clock; every header here is stamped)
ONE_PER_DOMAIN = sorted({listing.domain: listing.name for listing in CATALOG}.values())


def listing_of(name: str) -> Listing:
    cls = PACK[name].task_class
    assert cls is not None and issubclass(cls, SuiteTask)
    return cls.listing


def action_message(values: Any) -> dict[str, Any]:
    return {"layout": {"dim": [], "data_offset": 0}, "data": list(values)}


@dataclasses.dataclass
class Run:
    """One episode stepped both ways with the same actions."""

    sim: Simulation
    actions: list[np.ndarray]
    lab_rewards: list[float]
    suite_rewards: list[float]
    lab_observations: list[dict[str, np.ndarray]]  # tick 0 .. TICKS
    suite_observations: list[dict[str, np.ndarray]]
    topics: list[dict[str, Any]]  # each tick's /observation/* and /reward messages


@functools.cache
def run(name: str, seed: int) -> Run:
    """``TICKS`` ticks of the lab's path (``/action``, then ``Simulation.step``) and of
    the suite's own environment, with the same seeded in-range actions."""
    listing = listing_of(name)
    sim = Simulation(PACK[name], {}, seed=seed)
    env = suite.load(listing.domain, listing.task, task_kwargs={"random": seed})
    spec = env.action_spec()
    rng = np.random.default_rng(seed)
    first = env.reset()
    out = Run(sim, [], [], [], [], [dict(first.observation)], [])

    def observe() -> None:
        task = sim.task
        assert task.observation is not None
        out.lab_observations.append(dict(task.observation))
        stamp = stamp_of(sim.physics)
        out.topics.append(
            {
                o.name: task.observe(sim.physics, o.name, stamp)
                for o in task.observations
                if o.name.startswith("/observation/") or o.name == "/reward"
            }
        )

    observe()
    for _ in range(TICKS):
        action = rng.uniform(spec.minimum, spec.maximum, spec.shape)
        out.actions.append(action)
        sim.task.command("/action", action_message(action.tolist()))
        sim.step()
        out.lab_rewards.append(sim.reward)
        observe()
        timestep = env.step(action)
        out.suite_rewards.append(timestep.reward)
        out.suite_observations.append(dict(timestep.observation))
    return out


@pytest.fixture(params=NAMES)
def name(request: pytest.FixtureRequest) -> str:
    return str(request.param)


@pytest.mark.parametrize("seed", SEEDS)
def test_rewards_and_observations_are_the_suites_bit_for_bit(name, seed):
    """The lab's rewards, observations and observation topics equal dm_control's own
    environment's for the same seed and actions, exactly."""
    episode = run(name, seed)
    assert episode.lab_rewards == episode.suite_rewards
    assert episode.sim.total_reward == sum(episode.suite_rewards)
    assert len(episode.lab_observations) == len(episode.suite_observations) == TICKS + 1
    for tick, (lab, own, topics) in enumerate(
        zip(episode.lab_observations, episode.suite_observations, episode.topics, strict=True)
    ):
        assert list(lab) == list(own), tick
        for key, given in own.items():
            value = np.asarray(given)
            assert lab[key].dtype == value.dtype == np.float64, (tick, key)
            assert np.array_equal(lab[key], value), (tick, key)
            message = topics[f"/observation/{key}"]
            assert message["data"] == value.ravel().tolist(), (tick, key)
            assert [d["size"] for d in message["layout"]["dim"]] == list(value.shape)
        reward = episode.suite_rewards[tick - 1] if tick else 0.0
        assert topics["/reward"] == {"data": reward}, tick


def test_the_episode_is_as_long_as_the_suites():
    """With default parameters an episode ends on the step where dm_control's does."""
    spec = PACK["dmc-cartpole-balance"]
    listing = listing_of(spec.name)
    sim = Simulation(spec, {}, seed=4)
    env = suite.load(listing.domain, listing.task, task_kwargs={"random": 4})
    env.reset()
    ticks = 0
    while sim.running:
        sim.step()
        ticks += 1
        assert env.step(np.zeros(1)).last() == (not sim.running), ticks
    assert ticks == listing.steps == 1000
    assert sim.status in (EpisodeStatus.SUCCEEDED, EpisodeStatus.FAILED)


def test_catalogue_is_the_environments(name):
    """Each listing's episode length, timestep, actuators, observation keys and shapes and
    camera are what ``suite.load`` builds; the neutral action is within the spec; the
    recorded MJCF compiles to the suite's very model."""
    listing = listing_of(name)
    env = suite.load(listing.domain, listing.task, task_kwargs={"random": 0})
    model = env.physics.model
    assert env.control_timestep() == pytest.approx(listing.control_timestep, rel=1e-12)
    assert env._step_limit == pytest.approx(listing.steps, rel=1e-12)
    assert tuple(model.actuator(i).name for i in range(model.nu)) == listing.actuators
    spec = env.action_spec()
    assert spec.shape == (listing.action_size,)
    bounds = np.broadcast_to(spec.minimum, spec.shape), np.broadcast_to(spec.maximum, spec.shape)
    assert list(zip(*(b.tolist() for b in bounds), strict=True)) == list(listing.bounds)
    assert np.all(spec.minimum <= 0) and np.all(spec.maximum >= 0)  # zeros are an action
    observed = tuple((k, tuple(v.shape)) for k, v in env.observation_spec().items())
    assert observed == listing.observations
    assert model.camera(0).name == listing.camera
    xml, assets = model_of(listing)
    compiled = mujoco.MjModel.from_xml_string(xml, assets)
    assert _model_bytes(compiled) == _model_bytes(model.ptr)


def _model_bytes(model: mujoco.MjModel) -> bytes:
    buffer = np.zeros(mujoco.mj_sizeModel(model), dtype=np.uint8)
    mujoco.mj_saveModel(model, None, buffer)
    return buffer.tobytes()


def test_topics_are_declared_by_the_class_and_validate(name, registry):
    """The class names every topic without an episode (valid ROS names, one per
    observation key), and each message the task builds is valid for its type; /tf has
    every named body and the camera's optical frame in world."""
    spec = PACK[name]
    listing = listing_of(name)
    observations, commands = spec.topics()
    assert commands == ["/action"]
    keys = [f"/observation/{key}" for key, _ in listing.observations]
    assert observations[: len(keys)] == keys
    assert observations[len(keys) :] == [
        "/reward",
        "/joint_states",
        "/tf",
        "/camera/camera_info",
        "/camera/image/compressed",
    ]
    assert all(ROS_NAME.fullmatch(topic) for topic in observations + commands)
    sim = run(name, SEEDS[0]).sim
    task = sim.task
    stamp = stamp_of(sim.physics)
    for obs in task.observations:
        if obs.on_demand:
            continue  # the camera: test_camera_renders_a_jpeg_of_the_asked_size
        codec_for(registry, obs.type).normalize(task.observe(sim.physics, obs.name, stamp), NOW)
    codec_for(registry, ARRAY)
    model = sim.physics.model
    frames = task.observe(sim.physics, "/tf", stamp)["transforms"]
    assert {t["header"]["frame_id"] for t in frames} == {"world"}
    bodies = [model.body(b).name for b in range(1, model.nbody)]
    assert [t["child_frame_id"] for t in frames] == [*bodies, OPTICAL_FRAME]
    joints = task.observe(sim.physics, "/joint_states", stamp)
    hinges = [model.joint(j).name for j in range(model.njnt) if model.jnt_type[j] in (2, 3)]
    assert joints["name"] == hinges and len(joints["position"]) == len(hinges)


@pytest.mark.parametrize("name", ONE_PER_DOMAIN)
def test_camera_renders_a_jpeg_of_the_asked_size(name, registry):
    """The suite's camera 0 renders a JPEG of the size the parameters ask, with matching
    camera_info, on demand only."""
    sim = Simulation(PACK[name], {"camera_width": 64, "camera_height": 48}, seed=1)
    try:
        (image,) = [o for o in sim.task.observations if o.name == "/camera/image/compressed"]
        assert image.on_demand
        stamp = stamp_of(sim.physics)
        message = sim.task.observe(sim.physics, image.name, stamp)
        codec_for(registry, image.type).normalize(message, NOW)
        assert message["format"] == "jpeg"
        height, width, _, _ = simplejpeg.decode_jpeg_header(message["data"])
        assert (width, height) == (64, 48)
        info = sim.task.observe(sim.physics, "/camera/camera_info", stamp)
        assert (info["width"], info["height"]) == (64, 48)
        assert info["header"]["frame_id"] == message["header"]["frame_id"] == OPTICAL_FRAME
    finally:
        sim.close()


def test_bad_actions_are_refused_and_out_of_range_ones_clipped(name):
    """Before any command the action is zeros; a wrong length, NaN or infinity is refused
    naming what is wrong and changes nothing; values out of bounds are clipped to the
    spec's and the message is counted once."""
    sim = Simulation(PACK[name], {}, seed=2)
    task = sim.task
    size = listing_of(name).action_size
    assert np.array_equal(task.action(sim.physics), np.zeros(size))
    with pytest.raises(MessageError, match=rf"^data must hold {size} values?, one per actuator"):
        task.command("/action", action_message([0.0] * (size + 1)))
    with pytest.raises(MessageError, match=rf"got {size - 1}$"):
        task.command("/action", action_message([0.0] * (size - 1)))
    for bad in (math.nan, math.inf, -math.inf):
        values = [0.5] * size
        values[size - 1] = bad
        with pytest.raises(MessageError, match=rf"^data\[{size - 1}\] must be a finite number"):
            task.command("/action", action_message(values))
    assert np.array_equal(task.action(sim.physics), np.zeros(size)) and not task.clipped
    spec = sim.env.action_spec()
    task.command("/action", action_message([5.0] * size))
    task.command("/action", action_message([-5.0] * size))
    assert np.array_equal(task.action(sim.physics), np.broadcast_to(spec.minimum, (size,)))
    task.command("/action", action_message([0.25] * size))
    assert np.array_equal(task.action(sim.physics), np.full(size, 0.25))
    assert task.clipped == {"/action": 2}
    sim.step()
    assert sim.metrics()["clipped_commands"] == 2


def test_a_refused_action_is_an_error_for_its_sender_and_the_episode_goes_on(registry):
    """Through the robot's graph, a wrong-length /action raises MessageError at the
    publisher (the bridge's protocol error), no one hears it, and lockstep goes on."""
    graph = Graph(registry, name="dmc")
    robot = Robot(graph, PACK["dmc-reacher-easy"], {}, seed=1)
    try:
        client = graph.create_node("/controller")
        heard: list[Any] = []
        client.subscribe("/action", None, lambda m: heard.append(m.data))
        rewards: list[Any] = []
        client.subscribe("/reward", None, lambda m: rewards.append(m.data["data"]))
        publisher = client.advertise("/action", ARRAY)
        with pytest.raises(MessageError, match="must hold 2 values"):
            publisher.publish(action_message([1.0, 2.0, 3.0]))
        with pytest.raises(MessageError, match=r"data\[0\] must be a finite number"):
            publisher.publish(action_message([None, 0.0]))  # JSON null is NaN
        publisher.publish(action_message([0.5, -0.5]))
        assert len(heard) == 1
        answers: list[Any] = []
        client.call_service("/lab/step", None, answers.append)
        assert answers[0].response.data["success"] is True
        assert robot.sim.tick == 1 and len(rewards) == 2  # the latched tick 0, then tick 1
        assert np.array_equal(robot.sim.task.action(robot.sim.physics), [0.5, -0.5])
    finally:
        robot.close()


def test_the_threshold_decides_success_or_failure(monkeypatch):
    """At the episode's end it succeeded if the return reached the threshold, failed
    otherwise; metrics carry the return and the threshold; an endless (live) episode
    has no outcome."""
    spec = PACK["dmc-cartpole-balance"]
    cls = spec.task_class
    assert cls is not None
    listing = listing_of(spec.name)
    short = {"time_limit": 5 * listing.control_timestep}
    sim = Simulation(spec, short, seed=3)
    while sim.running:
        sim.step()
    assert sim.tick == 5
    achieved = sim.total_reward
    assert 0 < achieved < listing.threshold
    assert sim.status is EpisodeStatus.FAILED
    assert f"fell short of the threshold {listing.threshold:g}" in sim.reason
    assert "cut short" in sim.reason
    metrics = sim.metrics()
    assert metrics["success"] is False
    assert metrics["reward"] == achieved and metrics["return_threshold"] == listing.threshold

    for threshold, status in ((achieved, EpisodeStatus.SUCCEEDED), (achieved + 1e-9, None)):
        monkeypatch.setattr(cls, "listing", dataclasses.replace(listing, threshold=threshold))
        again = Simulation(spec, short, seed=3)
        while again.running:
            again.step()
        assert again.total_reward == achieved
        assert again.status is (status or EpisodeStatus.FAILED), again.reason
        assert again.metrics()["success"] is (status is not None)

    live = Simulation(spec, {}, seed=3, time_limit=math.inf)
    for _ in range(5):
        live.step()
    assert live.running and live.task.outcome(live.physics) is None


def test_the_time_limits_end_is_truncated_with_its_verdict_and_the_suites_own_is_not(
    monkeypatch,
):
    """An episode the time limit ended keeps its verdict as its status (what
    /lab/episode has always said) and is truncated (Simulation.truncated, Gymnasium's
    flag), as dm_control's last discount of 1 says; one the suite's own termination
    ended (discount 0) is not."""
    spec = PACK["dmc-cartpole-balance"]
    short = {"time_limit": 5 * listing_of(spec.name).control_timestep}
    sim = Simulation(spec, short, seed=3)
    assert not sim.truncated
    while sim.running:
        sim.step()
    assert (sim.status, sim.truncated) == (EpisodeStatus.FAILED, True)
    outcome = sim.task.outcome(sim.physics)
    assert outcome is not None and outcome.truncated and outcome.reason == sim.reason

    own = Simulation(spec, {}, seed=3)
    monkeypatch.setattr(own.task.inner, "get_termination", lambda physics: 0.0)
    own.step()
    assert (own.status, own.truncated, own.tick) == (EpisodeStatus.FAILED, False, 1)
    assert "the suite ended the episode at step 1" in own.reason


def test_seeds_beyond_numpys_are_still_seeds():
    """Seeds up to 2**32 - 1 are dm_control's own; larger ones (held-out suites) build,
    are reproducible, and differ from their low word."""
    assert random_for(2**32 - 1) == 2**32 - 1
    big = 2**40 + 7
    spec = PACK["dmc-reacher-hard"]
    positions = [Simulation(spec, {}, seed=s).physics.data.qpos.copy() for s in (big, big, 7)]
    assert np.array_equal(positions[0], positions[1])
    assert not np.array_equal(positions[0], positions[2])


def test_layouts_read_the_topics_in_order(name):
    """The export layout has one entry per observation number, in the suite's key order,
    and one per action value, each read from its topic's message; neutral values are 0."""
    spec = PACK[name]
    episode = run(name, SEEDS[0])
    layout_ = layout(spec)
    assert layout_ is LAYOUTS[name] and layout_.task == name
    observations, commands = spec.topics()
    assert layout_.observation_topics <= set(observations)
    assert layout_.action_topics == {"/action"} <= set(commands)
    messages = {
        topic: SimpleNamespace(data=message["data"])
        for topic, message in episode.topics[-1].items()
    }
    state = [e.extract(messages, e.topics[0]) for e in layout_.observation]
    flat = np.concatenate([np.ravel(v) for v in episode.suite_observations[-1].values()])
    assert state == flat.tolist()
    action = episode.actions[-1]
    sent = {"/action": SimpleNamespace(data=action.tolist())}
    assert [e.extract(sent, "/action") for e in layout_.action] == action.tolist()
    assert {e.neutral for e in (*layout_.observation, *layout_.action)} == {0.0}
    names = [e.name for e in (*layout_.observation, *layout_.action)]
    assert len(names) == len(set(names))


def test_the_action_vector_is_the_action_topic(name, registry):
    """``actions_of`` turns a vector into the /action message that acts it (clipped to
    the actuators' bounds, which are the spec's), and its neutral vector is zeros."""
    listing = listing_of(name)
    actions = actions_of(listing)
    assert [d.name for d in actions.dimensions] == list(listing.actuators)
    assert [(d.low, d.high) for d in actions.dimensions] == list(listing.bounds)
    sim = run(name, SEEDS[0]).sim
    vector = [5.0, *[0.125] * (listing.action_size - 1)]
    (message,) = actions.messages(vector).values()
    sim.task.command("/action", codec_for(registry, ARRAY).normalize(message, NOW))
    assert sim.task.action(sim.physics).tolist() == [listing.bounds[0][1], *vector[1:]]
    neutral = actions.messages([d.neutral for d in actions.dimensions])["/action"]
    assert neutral["data"] == [0.0] * listing.action_size


def test_importing_the_pack_builds_no_environment():
    """``import labd.sim.dmc`` compiles no model (it must stay as fast as the lab's other
    imports): with every way to build one made to fail, the import still succeeds."""
    code = (
        "import labd.sim.base, mujoco\n"
        "from dm_control import suite\n"
        "from dm_control.mujoco import Physics\n"
        "def refuse(*a, **k): raise SystemExit('an environment was built at import')\n"
        "suite.load = refuse\n"
        "Physics.from_xml_string = refuse\n"
        "mujoco.MjModel.from_xml_string = refuse\n"
        "import labd.sim.dmc as pack\n"
        "assert len(pack.TASKS) >= 20\n"
    )
    subprocess.run([sys.executable, "-c", code], cwd=ROOT, check=True, timeout=60)


def test_docs_table_every_task_with_its_threshold():
    """docs/tasks.md's pack table has one row per task: name, actions, observation keys,
    episode length and threshold as the catalogue says."""
    text = (ROOT / "docs" / "tasks.md").read_text()
    section = text[text.index("## The dm_control suite pack") :]
    rows = {
        cells[0].strip("` "): [c.strip() for c in cells[1:]]
        for line in section.splitlines()
        if line.startswith("| `dmc-")
        for cells in [line.strip("|").split("|")]
    }
    assert sorted(rows) == NAMES
    for listing in CATALOG:
        actions, keys, episode, threshold = rows[listing.name][:4]
        assert int(actions) == listing.action_size, listing.name
        assert re.findall(r"`([a-z_]+)`", keys) == [k for k, _ in listing.observations]
        assert episode == f"{listing.steps} steps of {listing.control_timestep:g} s", listing.name
        assert float(threshold) == listing.threshold, listing.name
        assert rows[listing.name][4] == listing.basis, listing.name


def test_docs_list_each_tasks_topics(name):
    """Each task's own section of docs/tasks.md names its observation and command topics
    exactly (as the shared suite, tests/labd/sim/test_tasks.py, checks)."""
    text = (ROOT / "docs" / "tasks.md").read_text()
    (body,) = [p for p in re.split(r"^## ", text, flags=re.M) if p.startswith(f"`{name}`")]
    observations, commands = PACK[name].topics()
    for section, topics in (("Observations", observations), ("Commands", commands)):
        (table,) = [p for p in re.split(r"^### ", body, flags=re.M) if p.startswith(section)]
        rows = [line.split("|")[1] for line in table.splitlines() if line.startswith("| `/")]
        assert {t for row in rows for t in re.findall(r"`(/[^`]*)`", row)} == set(topics)
