"""The example controllers, run as a trial would run them, against a lockstep robot."""

from __future__ import annotations

import os
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from labd.config import BridgeConfig, RobotConfig

pytestmark = pytest.mark.integration
ROOT = Path(__file__).resolve().parents[2]
EXAMPLES = ROOT / "controllers" / "examples"


def run_example(server, name: str) -> subprocess.CompletedProcess[str]:
    """Run the example's lab.toml command from its folder, as the sandbox would."""
    folder = EXAMPLES / name
    manifest = tomllib.loads((folder / "lab.toml").read_text())["controller"]
    command = manifest["command"]
    assert command[0] == "python"
    env = {**os.environ, "LAB_BRIDGE_URL": server.url, "PYTHONPATH": str(ROOT)}
    return subprocess.run(
        [sys.executable, *command[1:]],
        cwd=folder,
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )


def episode_of(server, robot: str) -> tuple[str, str, int]:
    sim = server.call(lambda: server.lab.robots[robot].sim)
    return server.call(lambda: (sim.status, sim.reason, sim.tick))


@pytest.mark.parametrize(
    ("example", "task", "seed"),
    [("icreate-maze", "icreate-maze", 11), ("pr2-pick-place", "pr2-table", 3)],
)
def test_example_succeeds_at_its_task(make_server, example, task, seed):
    """The example's lab.toml names its task; run on it, the controller exits 0 when the
    episode ends, and the episode ended because the robot did its task."""
    manifest = tomllib.loads((EXAMPLES / example / "lab.toml").read_text())["controller"]
    assert manifest["task"] == task
    server = make_server(
        BridgeConfig(port=0), robots=(RobotConfig("robot", task, seed=seed, live=False),)
    )
    result = run_example(server, example)
    assert result.returncode == 0, result.stdout[-2000:] + result.stderr[-2000:]
    status, reason, _ = episode_of(server, "robot")
    assert status == "succeeded", reason
    assert "succeeded" in result.stdout  # it saw the end, and said so


def test_the_maze_solver_runs_the_same_way_twice(make_server):
    """Same seed, same commands: the solver's log (with simulation times) and the
    episode's end are identical across runs."""
    runs = []
    for _ in range(2):
        server = make_server(
            BridgeConfig(port=0),
            robots=(RobotConfig("robot", "icreate-maze", seed=5, live=False),),
        )
        result = run_example(server, "icreate-maze")
        assert result.returncode == 0, result.stderr[-2000:]
        runs.append((result.stdout, episode_of(server, "robot")))
    assert runs[0] == runs[1]
    assert runs[0][1][0] == "succeeded"
