"""What every lab task is: a dm_control task that also speaks ROS topics.

A ``LabTask`` is an ordinary ``dm_control.suite.base.Task`` (``initialize_episode``,
``before_step``, ``get_observation``, ``get_reward``, ``get_termination``), so the
dm_control step loop runs it and an RL agent can use it in-process. On top of that it
declares the ROS side, which the robot node (``labd.sim.robot``) binds to a graph:

- ``commands``: topics the controller publishes (``/cmd_vel`` ...). ``command``
  receives each validated message; the task keeps what it needs (clipping values out
  of range and counting them, refusing NaN and infinity) and turns it into the
  dm_control action with ``action`` once per control tick.
- ``observations``: topics the lab publishes after each tick, built by ``observe``
  from the physics. Stamps are simulation time, so the same inputs give the same
  bytes.
- ``outcome``: whether the episode has ended, how, and why; ``metrics`` for the
  record (``success``, ``reward``, ...).

A task is built for one episode: the model itself may depend on the seed (the maze
does), so a new episode is a new task and a new physics (``labd.sim.simulation``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
from dm_control.rl import control
from dm_control.suite import base

from labd.errors import MessageError
from labd.sim.params import Params, Value
from repository.trial import EpisodeStatus

Stamp = dict[str, int]
LARGEST_SEED = 2**32 - 1  # numpy's RandomState takes integer seeds up to this


def random_state(seed: int) -> np.random.RandomState:
    """numpy's ``RandomState(seed)`` for any lab seed (0 to 2**63 - 1): the seed itself
    where numpy takes it, so those episodes stay as they were, else its two 32-bit halves
    (the held-out suites draw 63-bit seeds)."""
    if seed <= LARGEST_SEED:
        return np.random.RandomState(seed)
    return np.random.RandomState([seed & LARGEST_SEED, seed >> 32])


@dataclass(frozen=True)
class CommandTopic:
    """A topic the controller publishes and the task obeys."""

    name: str
    type: str
    doc: str


@dataclass(frozen=True)
class ObservationTopic:
    """A topic the lab publishes from the physics.

    ``period``: published every ``period`` control ticks (1: every tick; 0: once, when
    the episode begins, for what does not change: /tf_static, a goal).
    ``on_demand``: costly (a camera image); built only while someone subscribes.
    ``latched``: the last message is kept for subscribers that come later.
    """

    name: str
    type: str
    doc: str
    period: int = 1
    on_demand: bool = False
    latched: bool = True


@dataclass(frozen=True)
class Outcome:
    """How an episode ended.

    ``truncated``: its time limit ended it, and the task judged it there (the dm_control
    pack judges an episode's return at its end), so its ``status`` is the verdict while
    the task itself would go on: Gymnasium's ``truncated``, not ``terminated``.
    """

    status: EpisodeStatus  # SUCCEEDED, FAILED or TRUNCATED
    reason: str  # a sentence a person can act on
    truncated: bool = False


class LabTask(base.Task):  # type: ignore[misc]
    """A dm_control task with a ROS face. Subclasses fill in the class attributes.

    Note that dm_control's ``Task.initialize_episode`` calls ``after_step``; a task
    that counts events in ``after_step`` should not call it from its own
    ``initialize_episode``.
    """

    name: ClassVar[str]
    version: ClassVar[str]  # bump when behaviour changes; it goes into the manifest
    params: ClassVar[Params]
    commands: ClassVar[tuple[CommandTopic, ...]]
    observations: ClassVar[tuple[ObservationTopic, ...]]

    def __init__(self, params: Mapping[str, Value], random: np.random.RandomState) -> None:
        super().__init__(random=random)
        self.values = dict(params)
        self.clipped: dict[str, int] = {}  # commands clipped to their limits, per topic
        self.model_xml = ""  # the MJCF the factory compiled, for the trial record
        self.model_assets: dict[str, bytes] = {}  # files the MJCF names (textures)

    # -- the ROS side ------------------------------------------------------------------

    def command(self, topic: str, data: dict[str, Any]) -> None:
        """Take a validated message on one of ``commands`` (MessageError if refused)."""
        raise NotImplementedError

    def action(self, physics: Any) -> np.ndarray:
        """The dm_control action for the coming tick, from the commands kept so far."""
        raise NotImplementedError

    def observe(self, physics: Any, topic: str, stamp: Stamp) -> dict[str, Any] | None:
        """The message for ``topic`` now, or None to publish nothing this tick."""
        raise NotImplementedError

    def outcome(self, physics: Any) -> Outcome | None:
        """None while the episode runs; how it ended otherwise. At the time limit: None
        (the episode is then ``TRUNCATED``), or the task's verdict there with
        ``truncated=True``."""
        raise NotImplementedError

    def metrics(self, physics: Any) -> dict[str, bool | int | float]:
        """Figures for the record; at least ``success`` and ``reward``."""
        raise NotImplementedError

    # -- helpers for subclasses ----------------------------------------------------------

    def clip(self, topic: str, value: float, low: float, high: float) -> float:
        """``value`` within ``[low, high]``; clipping is counted against ``topic``."""
        if value < low or value > high:
            self.clipped[topic] = self.clipped.get(topic, 0) + 1
            return min(max(value, low), high)
        return value


def environment(
    physics: Any,
    task: LabTask,
    *,
    xml: str,
    assets: Mapping[str, bytes] | None = None,
    time_limit: float | None = None,
) -> control.Environment:
    """The dm_control environment of one episode, keeping the model for the record.

    Every task has the parameters ``time_limit`` (seconds) and ``control_rate`` (Hz);
    ``time_limit`` given here overrides the parameter (live robots have none unless
    their parameters give one).
    """
    task.model_xml = xml
    task.model_assets = dict(assets or {})
    limit = float(task.values["time_limit"]) if time_limit is None else time_limit
    return control.Environment(
        physics, task, time_limit=limit, control_timestep=1.0 / int(task.values["control_rate"])
    )


def finite(value: float, *path: str | int) -> float:
    """``value`` if it is a finite number; MessageError naming the field otherwise."""
    if not math.isfinite(value):
        raise MessageError("must be a finite number, got " + str(value), list(path))
    return value


def stamp_of(physics: Any) -> Stamp:
    """The simulation time as a ROS time (exact nanoseconds, no float drift)."""
    ns = round(float(physics.data.time) * 1e9)
    return {"sec": ns // 1_000_000_000, "nanosec": ns % 1_000_000_000}
