"""A policy learnt in-process runs in the lab: the messages of an episode of labd.gym,
replayed by a controller in a sandboxed trial, give the same episode."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
import textwrap
from pathlib import Path

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
