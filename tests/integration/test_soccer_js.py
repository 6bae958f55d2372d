"""Soccer, played alone in JavaScript: the example ball chaser's port
(controllers/examples/soccer-chaser-js, roslibjs in Node), run by ``labd run`` in a
bubblewrap trial, scores on the same tick as the Python chaser in-process on the same
seed, exits cleanly, and its record replays identically from its actions.

The two are not bit-identical: V8's ``Math.atan2`` is not glibc's and NumPy's two-element
dot is fused on x86-64 (the example's README), so their steers part by an ulp on some
ticks and the legs drift apart; fed the same observations, the port's commands are the
Python's up to those last bits."""

from __future__ import annotations

import json
import math
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from labd.recorder.reader import read_messages
from labd.replay import replay_filed
from labd.sim.simulation import Simulation
from tests.helpers.labs import shared_cache
from tests.helpers.sandboxes import make_backend
from tests.integration.test_soccer import chaser

NODE = shutil.which("node")
pytestmark = [
    pytest.mark.integration,
    pytest.mark.timeout(300),
    pytest.mark.skipif(NODE is None, reason="Node.js (node, version 20 or later) is not installed"),
]
ROOT = Path(__file__).resolve().parents[2]
CHASER_JS = ROOT / "controllers" / "examples" / "soccer-chaser-js"
NODE_MODULES = ROOT / "tests" / "js" / "node_modules"  # roslib, which the controller imports
SEED = 2  # both score at 9.975 s (399 ticks); on most seeds the legs drift apart earlier
KEYS = ("ball_ego_position", "opponent_goal_mid", "sensors_gyro")
ACT = """
import { readFileSync } from "node:fs";
import { act } from "./controller.mjs";
const ticks = JSON.parse(readFileSync(process.argv[2], "utf8"));
process.stdout.write(JSON.stringify(ticks.map((observed) => act(...observed))));
"""

Observed = list[list[float]]


def in_process(seed: int) -> tuple[Simulation, list[Observed], list[list[float]]]:
    """The Python chaser driving home in-process: the leg, each tick's observations and
    the commands it gave on them."""
    act = chaser().act
    sim = Simulation("soccer-1v1", {}, seed=seed)
    prefix = "/home/player_0/"
    observations: list[Observed] = []
    commands: list[list[float]] = []

    def observed(key: str) -> list[float]:
        message = sim.task.observe(sim.physics, f"{prefix}observation/{key}", {})
        assert message is not None
        return list(message["data"])

    while sim.running:
        observations.append([observed(key) for key in KEYS])
        commands.append(act(*observations[-1]))
        sim.task.command(prefix + "action", {"data": commands[-1]})
        sim.step()
    return sim, observations, commands


def js_act(observations: list[Observed], folder: Path) -> list[list[float]]:
    """The JavaScript ``act`` on each tick's observations, in Node (JSON both ways)."""
    if not (NODE_MODULES / "roslib").is_dir():
        pytest.fail(f"{NODE_MODULES} has no roslib: run `make setup` to install it")
    folder.mkdir()
    shutil.copy(CHASER_JS / "controller.mjs", folder)  # Node resolves roslib from its folder
    (folder / "node_modules").symlink_to(NODE_MODULES)
    (folder / "act.mjs").write_text(ACT)
    (folder / "observations.json").write_text(json.dumps(observations))
    assert NODE is not None
    done = subprocess.run([NODE, "act.mjs", "observations.json"], cwd=folder,
                          capture_output=True, text=True, timeout=60, check=False)  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    commands: list[list[float]] = json.loads(done.stdout)
    return commands


def test_the_js_chaser_scores_as_the_python_one_does_and_its_record_replays(
    cache: Path, tmp_path: Path
) -> None:
    """The port gives the Python commands up to the last bits, and through the lab it
    scores on the Python chaser's tick, exits 0, and replays verified."""
    make_backend("bwrap", cache)
    alone, observations, commands = in_process(SEED)
    assert alone.status.value == "succeeded" and alone.reason.startswith("home scored"), alone

    ported = js_act(observations, tmp_path / "act")
    assert len(ported) == len(commands)
    for tick, (js, py) in enumerate(zip(ported, commands, strict=True)):
        (js_roll, js_steer, js_kick), (py_roll, py_steer, py_kick) = js, py
        assert (js_roll, js_kick) == (py_roll, py_kick), (tick, js, py)
        assert math.isclose(js_steer, py_steer, rel_tol=0, abs_tol=1e-14), (tick, js, py)

    data = tmp_path / "data"
    shared_cache(data, cache)
    command = [sys.executable, "-m", "labd", "run", str(CHASER_JS), "--seed", str(SEED)]
    command += ["--sandbox", "bwrap", "--data", str(data), "--json"]
    done = subprocess.run(command, capture_output=True, text=True, timeout=240, check=False)
    result = json.loads(done.stdout)
    assert result["outcome"] == "success", (result.get("reason"), done.stderr[-2000:])
    assert result["exit_code"] == 0, result  # it saw the end and left by itself
    assert alone.reason in result["reason"], (alone.reason, result["reason"])
    metrics = result["metrics"]
    assert (metrics["home_goals"], metrics["away_goals"], metrics["ticks"]) == (1, 0, alone.tick)

    record = Path(result["mcap"])
    sent = sum(1 for _ in read_messages(record, topics=["/home/player_0/action"]))
    assert sent == alone.tick  # one command a tick, under home's name
    verdict = json.loads(replay_filed(record, tmp_path / "replay").verdict)
    assert verdict["verified"] is True, verdict
