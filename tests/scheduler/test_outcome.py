"""A trial's outcome in a sentence, from how the controller and the episode ended."""

from __future__ import annotations

import pytest

from labd.sim.simulation import Simulation
from sandbox.api import Exit, Limits
from scheduler.manifest import digest
from scheduler.outcome import judge
from tests.labd.sim.pointmass import TASK


@pytest.fixture
def sim():
    s = Simulation(TASK, {}, seed=1)
    for _ in range(3):
        s.step()
    return s


@pytest.mark.parametrize(
    ("exit_", "status", "reason"),
    [
        (Exit(0), "succeeded", "the controller exited with 0 at tick 3"),
        (
            Exit(1, stderr=b"Traceback...\nImportError: No module named 'foo'\n"),
            "failed",
            "controller exited with 1 at tick 3: ImportError: No module named 'foo'",
        ),
        (Exit(None, signal=9), "failed", "the controller was killed by SIGKILL at tick 3"),
        (
            Exit(None, signal=9, out_of_memory=True),
            "failed",
            "out of memory at tick 3 (the limit is",
        ),
        (
            Exit(None, signal=9, output_exceeded=True),
            "failed",
            "the controller printed more than 8 MiB",
        ),
        (Exit(None, signal=9, wall_exceeded=True), "failed", "time limit: the controller ran for"),
        (Exit(None, signal=24, cpu_exceeded=True), "failed", "CPU time limit of 3600 s"),
    ],
)
def test_how_the_controller_ended(sim, exit_, status, reason):
    """Each way a controller ends gives its status and a sentence saying why."""
    outcome = judge(exit_, sim, ended=False, limits=Limits())
    assert outcome.status == status and outcome.reason.startswith(reason)


def test_the_episode_end_wins(sim):
    """A controller stopped after its episode ended has done its part: succeeded."""
    outcome = judge(Exit(None, signal=15), sim, ended=True, limits=Limits())
    assert outcome.status == "succeeded"
    assert outcome.reason.startswith("the episode ended at tick 3: running")


def test_divergence_fails_the_trial():
    """A diverging physics fails the trial, with the simulation's reason."""
    s = Simulation(TASK, {}, seed=1)
    s.task.explode = True
    s.step()
    outcome = judge(Exit(0), s, ended=True, limits=Limits())
    assert outcome.status == "failed" and "physics diverged" in outcome.reason


def test_manifest_digest_is_canonical():
    """Key order does not change the digest; any value does."""
    assert digest({"a": 1, "b": [1, 2]}) == digest({"b": [1, 2], "a": 1})
    assert digest({"a": 1}) != digest({"a": 2})
