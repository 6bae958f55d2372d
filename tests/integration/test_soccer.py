"""Soccer, played alone: the example ball chaser (controllers/examples/soccer-chaser),
run by ``labd run`` in a bubblewrap trial against an away side that stands still,
scores as the same policy does in-process on the same seed, tick for tick (it spells
its team's topics, ``/player_0/...``: alone it plays home); its record holds both
sides' topics as the graph names them and replays identically from its actions."""

from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from labd.recorder.reader import read_messages
from labd.replay import replay_filed
from labd.sim.simulation import Simulation
from tests.helpers.labs import shared_cache
from tests.helpers.sandboxes import make_backend

pytestmark = [pytest.mark.integration, pytest.mark.timeout(300)]
ROOT = Path(__file__).resolve().parents[2]
CHASER = ROOT / "controllers" / "examples" / "soccer-chaser"
SEED = 2  # the chaser scores early: home scored at 9.975 s (399 ticks)
ARRAY = "std_msgs/msg/Float64MultiArray"


def chaser() -> Any:
    """The example's module (its ``act``), loaded from its file."""
    spec = importlib.util.spec_from_file_location("soccer_chaser", CHASER / "controller.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def in_process(seed: int) -> Simulation:
    """The chaser's policy driving home in-process, as the controller does through the lab."""
    act = chaser().act
    sim = Simulation("soccer-1v1", {}, seed=seed)
    prefix = "/home/player_0/"

    def observed(key: str) -> list[float]:
        message = sim.task.observe(sim.physics, f"{prefix}observation/{key}", {})
        assert message is not None
        return list(message["data"])

    while sim.running:
        command = act(observed("ball_ego_position"), observed("opponent_goal_mid"),
                      observed("sensors_gyro"))  # fmt: skip
        sim.task.command(prefix + "action", {"data": command})
        sim.step()
    return sim


def test_the_chaser_scores_as_it_does_in_process_and_its_record_replays(cache, tmp_path):
    make_backend("bwrap", cache)
    alone = in_process(SEED)
    assert alone.status.value == "succeeded" and alone.reason.startswith("home scored"), alone

    data = tmp_path / "data"
    shared_cache(data, cache)
    command = [sys.executable, "-m", "labd", "run", str(CHASER), "--seed", str(SEED)]
    command += ["--sandbox", "bwrap", "--data", str(data), "--json"]
    done = subprocess.run(command, capture_output=True, text=True, timeout=240, check=False)
    result = json.loads(done.stdout)
    assert result["outcome"] == "success", (result.get("reason"), done.stderr[-2000:])
    assert alone.reason in result["reason"], (alone.reason, result["reason"])
    metrics = result["metrics"]
    assert (metrics["home_goals"], metrics["away_goals"], metrics["ticks"]) == (1, 0, alone.tick)

    record = Path(result["mcap"])
    topics = {m.topic for m in read_messages(record)}
    assert {"/home/player_0/action", "/home/score", "/away/score"} <= topics
    assert "/away/player_0/observation/ball_ego_position" in topics  # both sides recorded
    assert "/away/player_0/action" not in topics  # the away side stood still
    verdict = json.loads(replay_filed(record, tmp_path / "replay").verdict)
    assert verdict["verified"] is True, verdict
