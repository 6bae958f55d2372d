"""The registry of tasks: each task is one module (or package) that declares everything
the lab needs of it, and the lab finds tasks as plugins.

A task module defines a ``TaskSpec`` (its factory and parameters, its topics through its
``LabTask`` class, its export layout, the camera its records are rendered with, its
episode suites, its live page, its starting script for the playground, its docs). The
lab's other parts ask the spec; nothing else is keyed by a task's name.

Tasks are found through the Python entry points of the group ``labd.tasks`` (as
dm_control's suite collects its domains, but across installed packages): each entry
point names a ``TaskSpec`` or a collection of them (a pack), e.g. in a package's
``pyproject.toml``::

    [project.entry-points."labd.tasks"]
    my-task = "my_package.task:TASK"        # one TaskSpec
    my-pack = "my_package.pack:TASKS"       # a tuple (or list) of TaskSpecs

The lab's own tasks are registered the same way by its own package. A plugin that fails
to import, names no TaskSpec, repeats a task's name or declares a topic the lab keeps
for itself is a **problem**: it is left out with its reason (``problems()``: shown by
``labd tasks`` and at ``labd serve`` start), and every other task still works.

Packs declare **benchmarks** the same way (``repository.benchmark``), through the group
``labd.benchmarks``: each entry point names a ``Benchmark`` or a tuple (or list) of them::

    [project.entry-points."labd.benchmarks"]
    my-pack = "my_package.pack:BENCHMARKS"

A benchmark plugin that fails to import or names no Benchmark, and a benchmark that
repeats another's name or names a task (or a suite of it) the lab does not have, is left
out with its reason (``benchmark_problems()``, logged as a warning).
"""

from __future__ import annotations

import copy
import dataclasses
import difflib
import logging
import re
import threading
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from importlib import metadata
from pathlib import Path
from typing import TYPE_CHECKING, Any

from labd.errors import LabError, UnknownTaskError
from labd.sim.params import Params, Value
from repository.benchmark import Benchmark
from repository.evaluation import Suite

if TYPE_CHECKING:
    from labd.sim.base import LabTask
    from repository.export import Layout

log = logging.getLogger("labd.sim.registry")
GROUP = "labd.tasks"
BENCHMARK_GROUP = "labd.benchmarks"
NAME = re.compile(r"[a-z0-9][a-z0-9_.-]{0,63}")
# names the robot node and the lab's live robots keep for themselves
LAB_TOPICS = frozenset(
    {
        "/clock",
        "/lab/episode",
        "/lab/step",
        "/lab/reset",
        "/lab/drive",
        "/lab/release",
        "/lab/driver",
        "/ux/events",
        "/rosout",
    }
)


@dataclass(frozen=True)
class Console:
    """A task's live page: a template of ``labd/web/templates`` (``robot_generic.html``:
    the camera, the model in 3D, a slider per action dimension, plots of the numeric
    observations) and the interfaces a session may be shown, the first the
    default (a study draws between the first two)."""

    template: str = "robot_generic.html"
    interfaces: tuple[str, ...] = ("video",)


GENERIC = Console()


@dataclass(frozen=True)
class Dimension:
    """One value of a task's action vector: where it goes in which command message.

    ``path`` is a dotted path into the message (``linear.x``; ``data.3`` and
    ``points.0.positions.2`` index lists), set in a copy of the topic's template."""

    name: str  # e.g. cmd_vel.linear.x
    topic: str
    path: str
    low: float
    high: float
    neutral: float = 0.0  # what the robot does before any command


@dataclass(frozen=True)
class Actions:
    """A task's commands as one vector of numbers: what an in-process learner acts with
    (``labd.gym``) and the generic live page slides, turned into the messages a
    controller would publish (``messages``), so a policy learnt one way runs the other.

    ``templates``: per command topic, its type and a message each vector is set into
    (fields not named by a dimension keep the template's values)."""

    dimensions: tuple[Dimension, ...]
    templates: Mapping[str, tuple[str, Mapping[str, Any]]]

    def messages(self, vector: Sequence[float]) -> dict[str, dict[str, Any]]:
        """The command messages, by topic, that ``vector`` stands for."""
        if len(vector) != len(self.dimensions):
            raise ValueError(f"an action has {len(self.dimensions)} values, not {len(vector)}")
        made = {
            topic: copy.deepcopy(dict(message)) for topic, (_, message) in self.templates.items()
        }
        for dimension, value in zip(self.dimensions, vector, strict=True):
            clipped = min(max(float(value), dimension.low), dimension.high)
            _set(made[dimension.topic], dimension.path.split("."), clipped)
        return made

    def describe(self) -> dict[str, Any]:
        """As JSON, for the live page."""
        return {
            "dimensions": [dataclasses.asdict(d) for d in self.dimensions],
            "templates": {
                t: {"type": kind, "message": m} for t, (kind, m) in self.templates.items()
            },
        }


def _set(message: Any, path: list[str], value: float) -> None:
    here = message
    for key in path[:-1]:
        here = here[int(key)] if isinstance(here, list) else here[key]
    last = path[-1]
    if isinstance(here, list):
        here[int(last)] = value
    else:
        here[last] = value


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
    # Its exports' rows (repository.export); None: the MCAP records are its data.
    layout: Layout | None = None
    # The model's camera that replays, videos and exports render (None: none).
    camera: str | None = None
    console: Console = GENERIC  # its live robots' page
    # The live robot ``labd serve`` hosts for it when told of no robots (None: none).
    robot: str | None = None
    # Its commands as a vector of numbers (labd.gym, the generic live page); None: none.
    actions: Actions | None = None
    # Its sides, when teams play it (soccer: home, away): each side's topics are under
    # /SIDE, and a controller sees its side's as / (labd.graph.names.Namespace); a lone
    # controller plays the first. Empty: one controller sees every topic as it is.
    sides: tuple[str, ...] = ()
    # Its observations are built in normal form (labd.graph.codec: every field, in
    # order, of the exact type), so the robot publishes them without validating them
    # again. The lab's own tasks are held to it by tests/labd/sim/test_normal_form.py;
    # a task from elsewhere is validated unless it says so.
    normal_form: bool = False

    def suite(self, name: str) -> Suite | None:
        return next((s for s in self.suites if s.name == name), None)

    def topics(self) -> tuple[list[str], list[str]]:
        """The task's observation topics and its command (action) topics."""
        if self.task_class is None:
            return [], []
        observations = [o.name for o in self.task_class.observations]
        return observations, [c.name for c in self.task_class.commands]


class Registry:
    """The tasks and benchmarks of the installed plugins, loaded once, on first use
    (thread-safe)."""

    def __init__(
        self,
        entry_points: Callable[[], Iterable[Any]] | None = None,
        benchmark_points: Callable[[], Iterable[Any]] | None = None,
    ) -> None:
        self._entry_points = entry_points or (lambda: metadata.entry_points(group=GROUP))
        self._benchmark_points = benchmark_points or (
            lambda: metadata.entry_points(group=BENCHMARK_GROUP)
        )
        self._lock = threading.Lock()
        self._specs: dict[str, TaskSpec] | None = None
        self._problems: dict[str, str] = {}
        self._benchmarks: dict[str, Benchmark] | None = None
        self._benchmark_problems: dict[str, str] = {}

    def specs(self) -> Mapping[str, TaskSpec]:
        with self._lock:
            if self._specs is None:
                self._specs = self._load()
            return self._specs

    def problems(self) -> dict[str, str]:
        """Plugins left out (entry point ``NAME = module:attr`` -> why)."""
        self.specs()
        return dict(self._problems)

    def _load(self) -> dict[str, TaskSpec]:
        found: dict[str, TaskSpec] = {}
        for point in sorted(self._entry_points(), key=_own_first):
            where = f"{point.name} = {point.value}"
            try:
                loaded = point.load()
            except Exception as err:  # a plugin's own bug: it is reported, the rest runs
                log.warning("task plugin %s failed to load", where, exc_info=True)
                self._problems[where] = f"failed to import: {type(err).__name__}: {err}"
                continue
            specs = [loaded] if isinstance(loaded, TaskSpec) else loaded
            if not isinstance(specs, (list, tuple)) or not specs:
                self._problems[where] = "names no TaskSpec (nor a tuple or list of them)"
                continue
            for spec in specs:
                why = _refused(spec, found)
                if why:
                    self._problems[f"{where} ({getattr(spec, 'name', spec)!r})"] = why
                else:
                    found[spec.name] = spec
        for where, why in self._problems.items():
            log.warning("task plugin %s left out: %s", where, why)
        return found

    def benchmarks(self) -> Mapping[str, Benchmark]:
        """The benchmarks whose every task (and suite of it) this lab has."""
        specs = self.specs()  # first: it takes the lock itself
        with self._lock:
            if self._benchmarks is None:
                self._benchmarks = self._load_benchmarks(specs)
            return self._benchmarks

    def benchmark_problems(self) -> dict[str, str]:
        """Benchmark plugins, or benchmarks of them, left out (``NAME = module:attr``,
        with the benchmark's name -> why)."""
        self.benchmarks()
        return dict(self._benchmark_problems)

    def _load_benchmarks(self, specs: Mapping[str, TaskSpec]) -> dict[str, Benchmark]:
        found: dict[str, Benchmark] = {}
        problems = self._benchmark_problems
        for point in sorted(self._benchmark_points(), key=_own_first):
            where = f"{point.name} = {point.value}"
            try:
                loaded = point.load()
            except Exception as err:  # a plugin's own bug: it is reported, the rest runs
                log.warning("benchmark plugin %s failed to load", where, exc_info=True)
                problems[where] = f"failed to import: {type(err).__name__}: {err}"
                continue
            declared = [loaded] if isinstance(loaded, Benchmark) else loaded
            if not isinstance(declared, (list, tuple)) or not declared:
                problems[where] = "names no Benchmark (nor a tuple or list of them)"
                continue
            for benchmark in declared:
                why = _benchmark_refused(benchmark, found, specs)
                if why:
                    problems[f"{where} ({getattr(benchmark, 'name', benchmark)!r})"] = why
                else:
                    found[benchmark.name] = benchmark
        for where, why in problems.items():
            log.warning("benchmark plugin %s left out: %s", where, why)
        return found


def _own_first(point: Any) -> tuple[bool, str]:
    """The lab's own tasks first (a plugin repeating one of their names is the one left
    out), each group in the order of the entry points' names."""
    return (not str(point.value).startswith("labd."), str(point.name))


def _refused(spec: Any, found: Mapping[str, TaskSpec]) -> str:
    """Why ``spec`` cannot be a task of this lab ("" if it can)."""
    if not isinstance(spec, TaskSpec):
        return f"is a {type(spec).__name__}, not a TaskSpec"
    if not NAME.fullmatch(spec.name):
        return (
            "its name must be lowercase letters, digits, '.', '_' and '-' (at most 64),"
            " starting with a letter or digit"
        )
    if spec.name in found:
        return f"the task {spec.name!r} is registered already; give it another name"
    observations, commands = spec.topics()
    clash = sorted(set(observations + commands) & LAB_TOPICS)
    if clash:
        return f"declares {', '.join(clash)}, which the lab keeps for itself"
    return ""


def _benchmark_refused(
    benchmark: Any, found: Mapping[str, Benchmark], specs: Mapping[str, TaskSpec]
) -> str:
    """Why ``benchmark`` cannot be one of this lab's ("" if it can)."""
    if not isinstance(benchmark, Benchmark):
        return f"is a {type(benchmark).__name__}, not a Benchmark"
    if benchmark.name in found:
        return f"the benchmark {benchmark.name!r} is declared already; give it another name"
    for each in benchmark.tasks:
        spec = specs.get(each.task)
        if spec is None:
            return f"names the task {each.task!r}, which this lab does not have"
        if spec.suite(each.suite) is None:
            return f"names the suite {each.suite!r} of {each.task}, which has no such suite"
    return ""


REGISTRY = Registry()


def names() -> list[str]:
    return list(REGISTRY.specs())


def problems() -> dict[str, str]:
    """The task plugins that were left out, and why."""
    return REGISTRY.problems()


def get(name: str) -> TaskSpec:
    spec = REGISTRY.specs().get(name)
    if spec is None:
        raise UnknownTaskError(name, names())
    return spec


def benchmarks() -> list[Benchmark]:
    """The benchmarks of the installed plugins, the lab's own first."""
    return list(REGISTRY.benchmarks().values())


def benchmark_problems() -> dict[str, str]:
    """The benchmark plugins (or benchmarks) that were left out, and why."""
    return REGISTRY.benchmark_problems()


def benchmark(name: str) -> Benchmark:
    """The benchmark ``name`` (``LabError`` naming the known ones if there is none)."""
    found = REGISTRY.benchmarks()
    if name not in found:
        close = difflib.get_close_matches(name, list(found), n=1)
        hint = f" (did you mean {close[0]}?)" if close else ""
        known = ", ".join(found) or "none"
        raise LabError(f"no benchmark {name!r}{hint}; the benchmarks are {known}")
    return found[name]


def default_robots() -> list[tuple[str, str]]:
    """The live robots ``labd serve`` hosts when told of none: (robot name, task) of each
    task that declares one."""
    return [(spec.robot, name) for name, spec in REGISTRY.specs().items() if spec.robot]


def validate(name: str, given: Mapping[str, Any]) -> dict[str, Value]:
    """The full parameter values of task ``name`` (ParamError if any is unacceptable)."""
    return get(name).params.validate(given)
