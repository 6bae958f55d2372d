"""labd.gym: the lab's tasks as Gymnasium environments, stepped in-process exactly as the
robot node steps them in a trial."""

from __future__ import annotations

import dataclasses
import math
import subprocess
import sys
from pathlib import Path
from typing import Any

import gymnasium
import numpy as np
import pytest
from dm_control import suite
from gymnasium.utils.env_checker import check_env

from labd.errors import EpisodeOverError
from labd.graph.graph import Graph, Side
from labd.graph.types import TypeRegistry
from labd.gym import LabEnv, env_id, learnable, register_all
from labd.recorder import Recorder
from labd.recorder.reader import read_messages
from labd.sim import registry
from labd.sim.robot import Robot
from repository.export import Source, read_episodes
from repository.well_known import EPISODE

# Small episodes: the checks step a few ticks, and none renders a large image.
SMALL: dict[str, dict[str, Any]] = {
    "icreate-maze": {"maze_size": 5, "camera_width": 32, "camera_height": 24, "time_limit": 2.0},
    "pr2-table": {"objects": 1, "camera_width": 32, "camera_height": 24, "time_limit": 1.0},
}
TASKS = sorted(SMALL)


def make(task: str, **kwargs: Any) -> LabEnv:
    env = gymnasium.make(f"labd/{task}-v1", params=SMALL[task], **kwargs).unwrapped
    assert isinstance(env, LabEnv)
    return env


def random_actions(env: LabEnv, seed: int, ticks: int) -> list[np.ndarray]:
    """Actions drawn over each dimension's range and a quarter of it beyond either end,
    so some are clipped."""
    low, high = env.action_space.low, env.action_space.high
    span = high - low
    rng = np.random.default_rng(seed)
    return [rng.uniform(low - span / 4, high + span / 4) for _ in range(ticks)]


def run(env: LabEnv, seed: int, actions: list[np.ndarray]) -> tuple[list[Any], list[float]]:
    """The observations (tick 0 on) and rewards of an episode, until it ends or the
    actions run out."""
    observation, _ = env.reset(seed=seed)
    observations, rewards = [observation], []
    for action in actions:
        observation, reward, terminated, truncated, _ = env.step(action)
        observations.append(observation)
        rewards.append(float(reward))
        if terminated or truncated:
            break
    return observations, rewards


# Gymnasium warns of these two by design: the observation's entries are unbounded, and
# each action is in the units of its message (m/s, rad), not normalized to [-1, 1].
@pytest.mark.filterwarnings("ignore:.*A Box observation space m:UserWarning")
@pytest.mark.filterwarnings("ignore:.*For Box action spaces, we recommend:UserWarning")
@pytest.mark.parametrize("task", TASKS)
def test_gymnasium_check_env_passes(task):
    """Gymnasium's own checker passes: spaces, seeding, determinism, data not reused,
    rendering, closing twice."""
    env = make(task, render_mode="rgb_array")
    try:
        check_env(env)
    finally:
        env.close()


@pytest.mark.parametrize("task", TASKS)
def test_spaces_are_the_actions_and_the_layout(task):
    """The action space is the task's Actions dimensions, float64 with their bounds; the
    observation space has one float32 per layout observation entry."""
    spec = registry.get(task)
    assert spec.actions is not None and spec.layout is not None
    env = make(task)
    assert env.action_space.dtype == np.float64
    assert env.action_space.low.tolist() == [d.low for d in spec.actions.dimensions]
    assert env.action_space.high.tolist() == [d.high for d in spec.actions.dimensions]
    assert env.observation_space.shape == (len(spec.layout.observation),)
    assert env.observation_space.dtype == np.float32


@pytest.mark.parametrize("task", TASKS)
def test_the_same_seed_and_actions_give_the_same_episode(task):
    """Twice the same seed and actions: the same observations and rewards, bit for bit;
    another seed, another episode."""
    env = make(task)
    actions = random_actions(env, 0, 8)
    first = run(env, 11, actions)
    again = run(env, 11, actions)
    other = run(env, 10, actions)
    env.close()
    assert [o.tobytes() for o in first[0]] == [o.tobytes() for o in again[0]]
    assert first[1] == again[1]
    assert [o.tobytes() for o in first[0]] != [o.tobytes() for o in other[0]]
    assert first[1] != other[1]


def robot_episode(
    task: str, seed: int, messages: list[dict[str, dict[str, Any]]], folder: Path
) -> Path:
    """Drive the lab's robot node on a graph, recorded, publishing ``messages[k]`` before
    step k, as a controller would; the record."""
    spec = registry.get(task)
    assert spec.actions is not None
    graph = Graph(TypeRegistry.shared(), name="gym-test")
    robot = Robot(graph, task, SMALL[task], seed)
    topics = {o.name for o in robot.sim.task.observations}
    recorder = Recorder(graph, folder, digest_topics=topics)
    client = graph.create_node("/controller", side=Side.CLIENT)
    publishers = {
        topic: client.advertise(topic, kind) for topic, (kind, _) in spec.actions.templates.items()
    }
    try:
        robot.publish()
        for tick in messages:
            for topic, message in tick.items():
                publishers[topic].publish(message)
            answers: list[Any] = []
            client.call_service("/lab/step", None, answers.append)
            assert answers[0].response.data["success"]
    finally:
        recorder.finish()
        robot.close()
    return recorder.path


@pytest.mark.parametrize("task", TASKS)
def test_an_episode_here_is_the_robots_episode(task, tmp_path):
    """The same seed and the messages the actions stand for, published to the robot node
    on a graph: the same reward every tick, and the export of its record has exactly the
    observations of the environment as its rows."""
    env = make(task)
    spec = env.task_spec
    actions = random_actions(env, 1, 12)
    observations, rewards = run(env, 5, actions)
    env.close()
    messages = [spec.actions.messages(a.tolist()) for a in actions[: len(rewards)]]
    record = robot_episode(task, 5, messages, tmp_path / "record")

    store = TypeRegistry.shared().typestore
    lab_rewards = {}
    for m in read_messages(record, topics=[EPISODE]):
        episode = store.deserialize_cdr(m.data, "lab_msgs/msg/Episode")
        lab_rewards[episode.tick] = episode.reward
    assert [lab_rewards[k] for k in range(1, len(rewards) + 1)] == rewards

    (episode,) = read_episodes(Source(record, {}), dataclasses.replace(spec.layout, cameras=()))
    rows = np.array(episode.state, dtype=np.float32)
    assert rows.tobytes() == np.array(observations[: len(rows)]).tobytes()
    assert len(rows) == len(rewards)


def test_reset_without_a_seed_draws_the_next_from_np_random():
    """reset(seed=N) is the lab's seed N; a reset without one draws the next seed from
    the generator that N seeded, the same in every process."""
    env, twin = make("icreate-maze"), make("icreate-maze")
    assert env.reset(seed=5)[1]["seed"] == 5
    twin.reset(seed=5)
    drawn = env.reset()[1]["seed"]
    assert drawn == twin.reset()[1]["seed"] and drawn != 5
    assert env.reset()[1]["seed"] != drawn
    with pytest.raises(ValueError, match="seed must be between 0 and 2\\*\\*63 - 1"):
        env.reset(seed=2**63)
    env.close()
    twin.close()


def test_bad_actions_are_clear_errors():
    """An action of the wrong shape, or with NaN or infinity, is a ValueError naming what
    is wrong; the episode has not moved."""
    env = make("icreate-maze")
    env.reset(seed=0)
    for action, says in (
        (np.zeros(3), r"is 2 numbers \(cmd_vel.linear.x, cmd_vel.angular.z\), got shape \(3,\)"),
        (np.zeros((1, 2)), r"got shape \(1, 2\)"),
        ("fast", r"is 2 numbers, got str"),
        ([0.1, float("nan")], r"action\[1\] \(cmd_vel.angular.z\) must be a finite number"),
        ([float("inf"), 0.0], r"action\[0\] \(cmd_vel.linear.x\) must be a finite number"),
    ):
        with pytest.raises(ValueError, match=says):
            env.step(action)
    assert env.simulation.tick == 0
    env.close()


def test_out_of_range_values_are_clipped_and_counted_once_per_message():
    """A value beyond its dimension is clipped as Actions.messages does and counted once
    for its message, as the task counts: not again when the task clips it too."""
    env = make("icreate-maze")
    env.reset(seed=0)
    clipped = env.simulation.task.clipped

    env.step(np.array([10.0, 0.0]))  # clipped by the dimension only
    assert clipped == {"/cmd_vel": 1}
    assert env.simulation.task.wheels.tolist() == pytest.approx([0.5, 0.5])
    env.step(np.array([0.5, 4.0]))  # in range, but faster than the wheels: the task counts
    assert clipped == {"/cmd_vel": 2}
    env.step(np.array([10.0, 10.0]))  # both: one message, counted once
    assert clipped == {"/cmd_vel": 3}
    _, _, _, _, info = env.step(np.array([0.1, 0.1]))
    assert info["metrics"]["clipped_commands"] == 3
    env.close()


def test_the_episode_ends_terminated_or_truncated_and_then_refuses_steps():
    """The time limit truncates (status and reason in info); a step after the end is the
    lab's EpisodeOverError."""
    env = make("icreate-maze")  # 2 s at 10 Hz
    env.reset(seed=0)
    for _ in range(19):
        assert env.step(np.zeros(2))[2:4] == (False, False)
    _, _, terminated, truncated, info = env.step(np.zeros(2))
    assert (terminated, truncated, info["status"], info["tick"]) == (False, True, "truncated", 20)
    assert info["reason"] == "the time limit of 2 s was reached"
    with pytest.raises(EpisodeOverError):
        env.step(np.zeros(2))
    env.close()


BALANCE = "dmc-cartpole-balance"
# A linear policy on the observation (controllers/examples/dmc-cartpole-balance): it
# keeps the pole up for the whole episode, a return of about 1000.
GAINS = np.array([0.2, 0.0, 4.0, 0.4, 0.6], dtype=np.float32)


def balanced(env: LabEnv, seed: int) -> list[tuple[bool, bool, dict[str, Any]]]:
    """The terminated and truncated flags and the info of every step of an episode
    driven by ``GAINS``, to its end."""
    observation, _ = env.reset(seed=seed)
    steps = []
    while True:
        action = np.clip(GAINS @ observation, -1, 1).reshape(1)
        observation, _, terminated, truncated, info = env.step(action)
        steps.append((terminated, truncated, info))
        if terminated or truncated:
            return steps


def test_a_dm_control_time_limit_truncates_whether_the_return_succeeded_or_not():
    """A dmc episode is judged by its return at its time limit (/lab/episode says
    succeeded or failed, as it always has), and Gymnasium is told it was truncated, not
    terminated: the suite's episode would go on (dm_control's own last discount is 1 at
    its time limit), so an agent bootstraps there. A whole episode that balances, and
    one cut to 10 ticks that cannot reach the threshold."""
    whole = LabEnv(BALANCE)
    steps = balanced(whole, seed=0)
    assert len(steps) == 1000 and not any(t or u for t, u, _ in steps[:-1])
    terminated, truncated, info = steps[-1]
    assert (terminated, truncated, info["status"]) == (False, True, "succeeded"), info["reason"]
    whole.close()

    short = LabEnv(BALANCE, {"time_limit": 0.1})
    steps = balanced(short, seed=0)
    terminated, truncated, info = steps[-1]
    assert (len(steps), terminated, truncated, info["status"]) == (10, False, True, "failed")
    with pytest.raises(EpisodeOverError):
        short.step(np.zeros(1))
    short.close()

    # dm_control's own environment says the same of its time limit
    env = suite.load("cartpole", "balance", task_kwargs={"random": 0, "time_limit": 0.1})
    env.reset()
    timesteps = [env.step(np.zeros(1)) for _ in range(10)]
    assert timesteps[-1].last() and timesteps[-1].discount == 1.0


def test_a_diverged_physics_terminates():
    """A physics that blows up ends the episode for good (the lab fails it): terminated,
    not truncated, on a dmc task as on the maze."""
    for task, params in ((BALANCE, {}), ("icreate-maze", SMALL["icreate-maze"])):
        env = LabEnv(task, params)
        env.reset(seed=1)
        env.simulation.physics.data.qvel[0] = math.nan
        _, _, terminated, truncated, info = env.step(np.zeros(env.action_space.shape))
        assert (terminated, truncated, info["status"]) == (True, False, "failed"), task
        assert "diverged" in info["reason"]
        env.close()


def test_render_is_the_cameras_image():
    """rgb_array renders the task's camera at its parameters' size; without a render
    mode nothing; before a reset, Gymnasium's ResetNeeded; an unknown mode is refused."""
    env = make("icreate-maze", render_mode="rgb_array")
    with pytest.raises(gymnasium.error.ResetNeeded):
        env.render()
    env.reset(seed=0)
    image = env.render()
    assert isinstance(image, np.ndarray)
    assert (image.shape, image.dtype) == ((24, 32, 3), np.uint8)
    assert image.std() > 0  # a scene, not a blank buffer
    env.close()
    plain = make("icreate-maze")
    plain.reset(seed=0)
    assert plain.render() is None
    plain.close()
    with pytest.raises(ValueError, match="render_mode must be one of"):
        LabEnv("icreate-maze", SMALL["icreate-maze"], render_mode="human")


def test_every_learnable_task_is_registered_once():
    """register_all registers each task with actions, a layout and a whole-number
    version as labd/NAME-vVERSION; again, it changes nothing (and does not warn)."""
    ids = register_all()
    assert {"labd/icreate-maze-v1", "labd/pr2-table-v1"} <= set(ids)
    assert register_all() == ids
    for made in ids:
        assert gymnasium.registry[made].entry_point == "labd.gym:LabEnv"
    spec = registry.get("icreate-maze")
    assert env_id(spec) == "labd/icreate-maze-v1" and learnable(spec)
    assert not learnable(dataclasses.replace(spec, actions=None))
    assert not learnable(dataclasses.replace(spec, layout=None))
    assert not learnable(dataclasses.replace(spec, version="1.2"))


def test_a_fresh_interpreter_makes_an_environment_by_the_modules_name():
    """Gymnasium 1.x has no plugin entry points: naming the module in the id imports it,
    which registers the environments, with no import beforehand."""
    code = (
        "import gymnasium\n"
        "env = gymnasium.make('labd.gym:labd/icreate-maze-v1', params={'maze_size': 5})\n"
        "print(env.reset(seed=0)[1]['seed'], env.action_space.shape)\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=False
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ["0", "(2,)"]


@pytest.mark.parametrize("made", register_all())
def test_every_environment_steps_within_its_spaces(made):
    """Every registered environment, with its task's default parameters: a reset and
    steps of its neutral action (the robot left as it starts) and of a sampled one give
    observations in the space, float rewards and the lab's tick."""
    env = gymnasium.make(made).unwrapped
    assert isinstance(env, LabEnv)
    neutral = np.array([d.neutral for d in env.actions.dimensions])
    env.action_space.seed(0)
    observation, info = env.reset(seed=1)
    assert observation in env.observation_space and info["tick"] == 0
    for tick, action in enumerate((neutral, env.action_space.sample()), start=1):
        observation, reward, _, _, info = env.step(action)
        assert observation in env.observation_space
        assert isinstance(reward, float) and info["tick"] == tick
    env.close()
