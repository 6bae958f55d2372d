"""The registry of tasks, as dm_control's suite keeps one: a name to a factory.

Each task module defines ``TASK``, a ``TaskSpec``; ``get`` and ``names`` find them.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from labd.errors import UnknownTaskError
from labd.sim.params import Params, Value
from repository.evaluation import Suite

if TYPE_CHECKING:
    from labd.sim.base import LabTask

# name -> the module that defines it; imported only when the task is used.
MODULES: Mapping[str, str] = {
    "icreate-maze": "labd.sim.icreate.maze",
    "pr2-table": "labd.sim.pr2.table",
}


@dataclass(frozen=True)
class TaskSpec:
    """A registered task.

    ``build(values, seed)`` returns a ``dm_control.rl.control.Environment`` whose task
    is a ``LabTask``, for one episode; ``values`` are already validated.
    ``time_limit`` overrides the task's own (``float('inf')`` for live robots, unless their
    parameters give one).
    ``live_params`` are defaults for live robots (a faster control rate for a smooth
    camera, say); what a robot's configuration sets still wins.
    """

    name: str
    version: str
    doc: str
    params: Params
    build: Callable[..., Any]
    live_params: Mapping[str, Value] = field(default_factory=dict)
    # The LabTask class: its command and observation topics, without building an episode.
    task_class: type[LabTask] | None = None
    # Its episode suites for evaluations (repository.evaluation): a public dev suite,
    # a held-out test suite; a suite's version goes up whenever its episodes change.
    suites: tuple[Suite, ...] = ()
    # A roslibjs script for this task that /playground starts from (runs live and in a trial).
    playground: Path | None = None

    def suite(self, name: str) -> Suite | None:
        return next((s for s in self.suites if s.name == name), None)

    def topics(self) -> tuple[list[str], list[str]]:
        """The task's observation topics and its command (action) topics."""
        if self.task_class is None:
            return [], []
        observations = [o.name for o in self.task_class.observations]
        return observations, [c.name for c in self.task_class.commands]


def names() -> list[str]:
    return list(MODULES)


def get(name: str) -> TaskSpec:
    module = MODULES.get(name)
    if module is None:
        raise UnknownTaskError(name, names())
    spec = importlib.import_module(module).TASK
    assert isinstance(spec, TaskSpec)
    return spec


def validate(name: str, given: Mapping[str, Any]) -> dict[str, Value]:
    """The full parameter values of task ``name`` (ParamError if any is unacceptable)."""
    return get(name).params.validate(given)
