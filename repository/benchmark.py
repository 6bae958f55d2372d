"""A benchmark: a named set of tasks, each on one of its suites, whose episodes' scores
are normalized to [0, 1] so that they add up across tasks (issue 37).

Reinforcement-learning papers report the DeepMind Control Suite as a set, aggregated
over normalized scores (rliable: Agarwal et al. 2021). A task pack declares its
benchmarks as values of this module (``labd.sim.registry`` finds them through the entry
point group ``labd.benchmarks``, as it finds tasks through ``labd.tasks``); the API and
``labd tasks`` read them. This module is the declaration alone: pure, importable without
the simulator or the lab.

    Benchmark(name, doc, tasks)                   e.g. dmc-classic
    └── BenchmarkTask(task, suite="dev", normalize)
        └── Normalize(by=RETURN, scale=1000)      the return over 1000, clipped to [0, 1]
            Normalize(by=SUCCESS)                 1 if the episode succeeded, else 0

``normalized(task, episode)`` is an episode's score: it reads what the lab files for an
evaluation's episode (``repository.evaluation.EpisodeRow``), its ``outcome`` and its
``reward``, which is the task's ``reward`` metric (``repository.index.reward_of``): for
the dm_control pack, the episode's return, the suite's sum of rewards (0 to 1000).
"""

from __future__ import annotations

import math
import re
from enum import StrEnum
from typing import ClassVar

from pydantic import BaseModel, ConfigDict, Field, RootModel, field_validator, model_validator

from repository.evaluation import SUITE_NAME, EpisodeRow
from repository.trial import Outcome

NAME = re.compile(r"[a-z0-9][a-z0-9-]{0,63}", re.ASCII)  # a benchmark's
TASK_NAME = re.compile(r"[a-z0-9][a-z0-9_.-]{0,63}", re.ASCII)  # as labd.sim.registry's


class By(StrEnum):
    """What an episode's normalized score is made from."""

    RETURN = "return"  # its return (the ``reward`` metric) over a scale, clipped to [0, 1]
    SUCCESS = "success"  # 1 if it succeeded, else 0


class Normalize(BaseModel):
    """How an episode's score becomes a number in [0, 1].

    ``Normalize(by=Normalize.RETURN, scale=1000.0)``: the return over ``scale``, clipped
    to [0, 1]; ``Normalize(by=Normalize.SUCCESS)``: success alone (no scale)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    RETURN: ClassVar[By] = By.RETURN
    SUCCESS: ClassVar[By] = By.SUCCESS

    by: By
    scale: float | None = Field(
        default=None, description="by return: the return that scores 1 (none by success)"
    )

    @model_validator(mode="after")
    def _scaled_by_return_only(self) -> Normalize:
        if self.by is By.RETURN:
            if self.scale is None or not math.isfinite(self.scale) or self.scale <= 0:
                raise ValueError(
                    f"a return is normalized over a positive finite scale, not {self.scale!r}"
                )
        elif self.scale is not None:
            raise ValueError("a normalization by success takes no scale")
        return self

    def describe(self) -> str:
        """In words, for people."""
        if self.by is By.RETURN:
            return f"the return over {self.scale:g}, clipped to [0, 1]"
        return "1 if the episode succeeded, else 0"


class BenchmarkTask(BaseModel):
    """One task of a benchmark: which task, on which of its suites, normalized how."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    task: str = Field(description="a task's name, as the registry knows it")
    suite: str = Field(default="dev", description="one of the task's episode suites")
    normalize: Normalize

    @field_validator("task")
    @classmethod
    def _task_name(cls, value: str) -> str:
        if not TASK_NAME.fullmatch(value):
            raise ValueError(f"{value!r} is not a task's name")
        return value

    @field_validator("suite")
    @classmethod
    def _suite_name(cls, value: str) -> str:
        if not SUITE_NAME.fullmatch(value):
            raise ValueError(f"{value!r} is not a suite's name")
        return value


class Benchmark(BaseModel):
    """A named set of tasks, each on one suite, scored together.

    Its name is lowercase letters, digits and '-' (at most 64); it names each task once."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    name: str
    doc: str = Field(min_length=1, description="what it measures, in a sentence or two")
    tasks: tuple[BenchmarkTask, ...] = Field(min_length=1)

    @field_validator("name")
    @classmethod
    def _name(cls, value: str) -> str:
        if not NAME.fullmatch(value):
            raise ValueError(
                f"a benchmark's name is lowercase letters, digits and '-' (at most 64),"
                f" starting with a letter or digit, not {value!r}"
            )
        return value

    @field_validator("tasks")
    @classmethod
    def _each_task_once(cls, value: tuple[BenchmarkTask, ...]) -> tuple[BenchmarkTask, ...]:
        names = [t.task for t in value]
        again = sorted({n for n in names if names.count(n) > 1})
        if again:
            raise ValueError(f"a benchmark names each task once; {', '.join(again)} more than once")
        return value

    def task(self, name: str) -> BenchmarkTask | None:
        return next((t for t in self.tasks if t.task == name), None)


class BenchmarkList(RootModel[list[Benchmark]]):
    """The body of ``GET /api/benchmarks``: every benchmark of the lab."""


def normalized(task: BenchmarkTask, episode: EpisodeRow) -> float:
    """The normalized score, in [0, 1], of one ended episode of ``task``.

    Reads ``episode.outcome`` and, by return, ``episode.reward`` (the task's ``reward``
    metric: for the dm_control pack the episode's return). An episode that broke
    (``Outcome.ERROR``) scores 0 whatever its reward so far: a benchmark counts every
    episode, and a controller earns nothing from one it did not finish. ``ValueError``
    for an episode that has not ended (no outcome), or, by return, one that ended without
    a finite reward (its task reports no return: the benchmark is declared wrong).
    """
    if episode.outcome is None:
        raise ValueError(f"episode {episode.episode} (trial {episode.trial}) has not ended")
    if episode.outcome is Outcome.ERROR:
        return 0.0
    rule = task.normalize
    if rule.by is By.SUCCESS:
        return 1.0 if episode.outcome is Outcome.SUCCESS else 0.0
    reward = episode.reward
    if reward is None or not math.isfinite(reward):
        raise ValueError(
            f"episode {episode.episode} (trial {episode.trial}) of {task.task} ended with no"
            f" return (its reward is {reward!r}), so it cannot be normalized by return"
        )
    assert rule.scale is not None  # a normalization by return has one (Normalize)
    return min(max(reward / rule.scale, 0.0), 1.0)
