"""Trials of a dm_control pack task for real, in both sandboxes: the example cart-pole
controller, and controllers whose ``/action`` the lab refuses."""

from __future__ import annotations

import asyncio
import textwrap
from pathlib import Path

import pytest

from labd.replay import replay
from repository.trial import Order, Outcome
from scheduler.runner import RunOptions, run_trial

pytestmark = pytest.mark.integration
EXAMPLE = Path(__file__).resolve().parents[2] / "controllers" / "examples" / "dmc-cartpole-balance"
# A user's controller that sends /action wrong: its own line 12 is where it errs.
REFUSED = """\
import math

from controllers.client import Lab

ARRAY = "std_msgs/msg/Float64MultiArray"


def main(action):
    with Lab.connect() as lab:
        for _ in range(3):
            lab.publish("/action", ARRAY, {{"data": action}})
            lab.step()


main({action})
"""


def run(backend, cache, host, tmp_path, source, **kwargs):
    order = Order(repository=str(source), **kwargs)
    out = tmp_path / f"run-{len(list(tmp_path.glob('run-*')))}"
    return asyncio.run(
        run_trial(order, backend=backend, host=host, out=out, cache=cache, options=RunOptions())
    )


def test_the_cartpole_example_succeeds_and_reproduces(backend, cache, host, tmp_path):
    """The example's linear policy balances the pole for the whole episode (a return
    above the threshold of 900); the same seed gives the same data, another seed other
    data, and its actions alone replay its observations."""
    first = run(backend, cache, host, tmp_path, EXAMPLE, seed=1)
    assert first.outcome is Outcome.SUCCESS, first.reason
    assert first.metrics["success"] is True and first.metrics["reward"] > 999
    assert first.metrics["ticks"] == 1000
    second = run(backend, cache, host, tmp_path, EXAMPLE, seed=1)
    assert (second.data_digest, second.manifest_digest) == (
        first.data_digest,
        first.manifest_digest,
    )
    other_seed = run(backend, cache, host, tmp_path, EXAMPLE, seed=2)
    assert other_seed.outcome is Outcome.SUCCESS, other_seed.reason
    assert other_seed.data_digest != first.data_digest
    assert replay(first.mcap).verified


@pytest.mark.parametrize(
    ("action", "refusal"),
    [
        ("[0.0, 1.0]", "data must hold 1 value, one per actuator (slide), got 2"),
        ("[math.nan]", "data[0] must be a finite number, got"),
    ],
)
def test_a_refused_action_is_reported_at_the_controllers_own_line(
    backend, cache, host, tmp_path, action, refusal
):
    """A controller whose /action the lab refuses (the wrong length, a NaN) crashes with
    the client library's StatusError; the trial's reason says the lab's refusal and the
    controller's own file and line, not the library's that raised it."""
    folder = tmp_path / "code"
    folder.mkdir()
    (folder / "lab.toml").write_text(
        '[controller]\ncommand = ["python", "controller.py"]\ntask = "dmc-cartpole-balance"\n'
    )
    (folder / "controller.py").write_text(textwrap.dedent(REFUSED.format(action=action)))
    folder.chmod(0o755)
    result = run(backend, cache, host, tmp_path, folder, seed=0)
    assert result.outcome is Outcome.ERROR, result.reason
    assert "StatusError: the lab refused" in result.reason and refusal in result.reason
    assert result.reason.endswith("(/code/controller.py, line 12, in main)"), result.reason
