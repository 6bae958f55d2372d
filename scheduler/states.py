"""What the scheduler says about a trial and a worker, by value.

These words leave the scheduler: the API and the pages show them, a remote worker
reports them, and the ``labd`` command reads them back. So they live here, apart from
the machinery that produces them (the runner, the canaries, the queue, which import the
sandbox, git and the archive's index), and a client reads them without importing it.

    Stage    what a trial's worker is doing with it   (``scheduler.runner.Progress``)
    State    a worker's state as its canaries found it (``scheduler.canary``)
    Cancel   what cancelling a trial did              (``scheduler.queue.Queue.cancel``)
"""

from __future__ import annotations

from enum import StrEnum


class Stage(StrEnum):
    """What a trial's worker is doing with it: the runner's stages, then the worker's."""

    STARTING = "starting"
    PREPARING = "preparing"  # fetching, checking out, building the controller
    RUNNING = "running"  # the controller and the robot, in lockstep or on the wall clock
    FILING = "filing"  # the record stored and filed with the lab


class State(StrEnum):
    """A worker's state as its canaries found it; a remote worker reports it by value."""

    OK = "ok"  # its canaries reproduced, or it has none
    CHECKING = "checking"  # it is rerunning them
    OUT = "out"  # one did not reproduce: out of the pool, it claims nothing more


class Cancel(StrEnum):
    """What cancelling did."""

    CANCELLED = "cancelled"  # it was queued: it will never run
    STOPPING = "stopping"  # it runs: its worker stops it at its next heartbeat
    ENDED = "ended"  # it had ended already: nothing was done
