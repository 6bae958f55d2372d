"""A policy learnt in-process runs in the lab: the messages of an episode of labd.gym,
replayed by a controller in a sandboxed trial, give the same episode; a dm_control
policy run as a controller (controllers/examples/dmc-cartpole-balance) earns the
environment's rewards, bit for bit, and ends the way the environment says."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
import textwrap
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from labd.graph.types import TypeRegistry
from labd.gym import LabEnv
from labd.recorder.reader import read_messages
from repository.export import Source, read_episodes
from repository.well_known import EPISODE
from tests.helpers.labs import shared_cache
from tests.helpers.sandboxes import make_backend

pytestmark = [pytest.mark.integration, pytest.mark.timeout(300)]
ROOT = Path(__file__).resolve().parents[2]
BALANCE = ROOT / "controllers" / "examples" / "dmc-cartpole-balance"
TASK = "icreate-maze"
SEED = 7
PARAMS = {"maze_size": 5, "time_limit": 5.0}  # 50 ticks at 10 Hz
CONTROLLER = """\
import json

from controllers.client import EpisodeOver, Lab

with open("commands.json") as f:
    ticks = json.load(f)
with Lab.connect() as lab:
    for messages in ticks:
        for m in messages:
            lab.publish(m["topic"], m["type"], m["msg"])
        try:
            lab.step()
        except EpisodeOver:
            break
"""


def test_the_same_actions_in_process_and_through_the_lab_give_the_same_rewards(cache, tmp_path):
    """A seeded random episode here (actions beyond the limits included), its messages
    published tick by tick by a controller in a bwrap trial with the same seed: the
    record's reward on /lab/episode equals the environment's every tick, exactly, and the
    export of the record has the environment's observations as its rows."""
    make_backend("bwrap", cache)
    env = LabEnv(TASK, PARAMS)
    spec = env.actions
    low, high = env.action_space.low, env.action_space.high
    rng = np.random.default_rng(0)
    observation, _ = env.reset(seed=SEED)
    observations, rewards, ticks = [observation], [], []
    for _ in range(50):
        action = rng.uniform(1.25 * low, 1.25 * high)
        ticks.append(
            [
                {"topic": topic, "type": spec.templates[topic][0], "msg": message}
                for topic, message in spec.messages(action.tolist()).items()
            ]
        )
        observation, reward, terminated, truncated, info = env.step(action)
        observations.append(observation)
        rewards.append(float(reward))
        if terminated or truncated:
            break
    env.close()
    assert truncated and len(rewards) == 50  # the episode the lab will run to its end

    folder = tmp_path / "code"
    folder.mkdir()
    (folder / "lab.toml").write_text(
        f'[controller]\ncommand = ["python", "controller.py"]\ntask = "{TASK}"\n'
    )
    (folder / "controller.py").write_text(textwrap.dedent(CONTROLLER))
    (folder / "commands.json").write_text(json.dumps(ticks))
    folder.chmod(0o755)
    data = tmp_path / "data"
    shared_cache(data, cache)
    params = [arg for k, v in PARAMS.items() for arg in ("--param", f"{k}={v}")]
    command = [sys.executable, "-m", "labd", "run", str(folder), "--task", TASK]
    command += ["--sandbox", "bwrap", "--data", str(data), "--seed", str(SEED), *params, "--json"]
    done = subprocess.run(command, capture_output=True, text=True, timeout=240, check=False)
    result = json.loads(done.stdout)
    assert result["status"] == "finished", (result.get("reason"), done.stderr[-2000:])
    mcap = Path(result["mcap"])

    store = TypeRegistry.shared().typestore
    lab: dict[int, float] = {}
    for m in read_messages(mcap, topics=[EPISODE]):
        episode = store.deserialize_cdr(m.data, "lab_msgs/msg/Episode")
        lab[episode.tick] = episode.reward
        last = episode
    assert max(lab) == len(rewards) and last.status == "truncated"
    assert [lab[k] for k in range(1, len(rewards) + 1)] == rewards

    layout = dataclasses.replace(env.layout, cameras=())
    (episode_rows,) = read_episodes(Source(mcap, {}), layout)
    rows = np.array(episode_rows.state, dtype=np.float32)
    assert rows.tobytes() == np.array(observations[:-1]).tobytes()


def balance_in_process(seed: int, dtype: type[np.floating]) -> tuple[list[float], list[Any]]:
    """The rewards and the last step's (terminated, truncated, info) of an episode of
    labd/dmc-cartpole-balance-v1 driven by the example's linear policy computed in
    ``dtype`` (the environment's observation is float32)."""
    gains = np.array([0.2, 0.0, 4.0, 0.4, 0.6], dtype=dtype)
    env = LabEnv("dmc-cartpole-balance")
    observation, _ = env.reset(seed=seed)
    rewards = []
    while True:
        action = np.clip(gains @ observation.astype(dtype), -1, 1).reshape(1)
        observation, reward, terminated, truncated, info = env.step(action)
        rewards.append(float(reward))
        if terminated or truncated:
            env.close()
            return rewards, [terminated, truncated, info]


def test_a_dm_control_policy_earns_the_environments_rewards_and_ends_as_it_says(cache, tmp_path):
    """The example cart-pole controller, run by labd run in a bwrap trial, earns exactly
    the rewards of the environment driven by the same policy in float32, tick for tick;
    the episode ends at its time limit, which Gymnasium calls truncated (not terminated)
    while /lab/episode's status, the environment's info and the trial's outcome all say
    it succeeded. The same policy computed in float64 earns other rewards: that is why
    the controller computes in float32 (docs/tasks.md)."""
    make_backend("bwrap", cache)
    seed = 2
    rewards, (terminated, truncated, info) = balance_in_process(seed, np.float32)
    assert (terminated, truncated, info["status"]) == (False, True, "succeeded")
    assert len(rewards) == 1000
    float64, _ = balance_in_process(seed, np.float64)
    assert float64 != rewards and abs(sum(float64) - sum(rewards)) < 1e-3

    data = tmp_path / "data"
    shared_cache(data, cache)
    command = [sys.executable, "-m", "labd", "run", str(BALANCE), "--seed", str(seed)]
    command += ["--sandbox", "bwrap", "--data", str(data), "--json"]
    done = subprocess.run(command, capture_output=True, text=True, timeout=240, check=False)
    result = json.loads(done.stdout)
    assert result["outcome"] == "success", (result.get("reason"), done.stderr[-2000:])
    assert result["metrics"]["total_reward"] == sum(rewards)
    store = TypeRegistry.shared().typestore
    lab: dict[int, float] = {}
    for m in read_messages(Path(result["mcap"]), topics=[EPISODE]):
        episode = store.deserialize_cdr(m.data, "lab_msgs/msg/Episode")
        lab[episode.tick] = episode.reward
        last = episode
    assert [lab[k] for k in range(1, 1001)] == rewards
    assert (last.tick, last.status, last.reason) == (1000, info["status"], info["reason"])
