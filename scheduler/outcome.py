"""How a trial ended, in a sentence a person can act on."""

from __future__ import annotations

import signal
from dataclasses import dataclass

from labd.sim.simulation import Simulation
from sandbox.api import Exit, Limits

SUCCEEDED, FAILED, CANCELLED = "succeeded", "failed", "cancelled"
MiB = 1024 * 1024


@dataclass(frozen=True)
class Outcome:
    status: str  # succeeded, failed or cancelled
    reason: str


def judge(exit_: Exit, sim: Simulation, *, ended: bool, limits: Limits) -> Outcome:
    """The outcome of a trial whose controller ended as ``exit_``.

    The episode's end wins over how the controller went: a controller stopped after
    the episode ended has done its part. A physics divergence is a failure of the
    trial (the lab's model broke), not of the robot's task. A controller that exits
    with 0 having never stepped ran nothing: that is a failure too.
    """
    at = f"at tick {sim.tick}"
    if sim.diverged:
        return Outcome(FAILED, sim.reason)
    if ended:
        return Outcome(SUCCEEDED, f"the episode ended {at}: {sim.status}: {sim.reason}")
    if exit_.out_of_memory:
        return Outcome(FAILED, f"out of memory {at} (the limit is {limits.memory // MiB} MiB)")
    if exit_.output_exceeded:
        return Outcome(
            FAILED,
            f"the controller printed more than {limits.output // MiB} MiB {at}; it was stopped",
        )
    if exit_.wall_exceeded:
        return Outcome(
            FAILED, f"time limit: the controller ran for {limits.wall:g} s (stopped {at})"
        )
    if exit_.cpu_exceeded:
        return Outcome(FAILED, f"CPU time limit of {limits.cpu_seconds} s reached {at}")
    if exit_.code == 0 and sim.tick == 0:
        return Outcome(
            FAILED, "the controller exited with 0 before its first /lab/step: nothing ran"
        )
    if exit_.code == 0:
        return Outcome(SUCCEEDED, f"the controller exited with 0 {at}")
    if exit_.code is None:
        name = _signal_name(exit_.signal)
        return Outcome(FAILED, f"the controller was killed by {name} {at}")
    last = last_error_line(exit_.stderr)
    detail = f": {last}" if last else ""
    return Outcome(FAILED, f"controller exited with {exit_.code} {at}{detail}")


def last_error_line(stderr: bytes) -> str:
    """The last meaningful line of a controller's stderr (a traceback's last line)."""
    lines = [line.strip() for line in stderr.decode("utf-8", "replace").splitlines()]
    lines = [line for line in lines if line]
    return lines[-1][:300] if lines else ""


def _signal_name(number: int | None) -> str:
    if number is None:
        return "a signal"
    try:
        return signal.Signals(number).name
    except ValueError:
        return f"signal {number}"
