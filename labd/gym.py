"""Gymnasium environments of the lab's tasks: learn in-process, then submit the policy.

Every registered task that declares its commands as a vector (``TaskSpec.actions``) and
an export layout (``TaskSpec.layout``) is a Gymnasium environment, ``labd/TASK-vVERSION``
(``labd/icreate-maze-v1``, ``labd/pr2-table-v1``). It steps the lab's own task in this
process, the same ``Simulation``, seeds and dynamics as a trial, so an episode here and
a trial with ``--seed N`` are the same episode::

    import gymnasium

    env = gymnasium.make("labd.gym:labd/icreate-maze-v1", params={"maze_size": 7})
    observation, info = env.reset(seed=3)        # the lab's seed 3, exactly
    observation, reward, terminated, truncated, info = env.step(env.action_space.sample())

Tasks without ``actions`` or without a ``layout`` have no environment (nothing says
what a vector of numbers would command, or what the observation vector holds); nor
has a task whose version is not a whole number, which a Gymnasium id cannot spell.

**What a step is.** A trial's controller publishes its commands, then calls
``/lab/step``; the robot hands each command, validated and completed by the graph's
codec, to the task, steps one control tick and publishes that tick's observations.
``LabEnv.step`` does the same without the graph: ``Actions.messages(action)``, each
message completed by the same codec as the bridge's (``Codec.normalize``, stamped in
simulation time), ``task.command`` for each, ``Simulation.step``. So the messages a
policy's actions stand for, published by a controller, make the same ticks.

**Spaces.** The observation is the layout's observation entries (docs/tasks.md lists
them), float32 as in an export, computed by the same ``Entry`` functions from the
newest message of each topic the task published at that tick (their neutral value
before any): a row of an export of the trial is the observation here. The messages
are the codec's rosbags objects (``Codec.to_rosbags``), which the entries read as they
read an export's decoded messages; encoding to CDR and decoding as an export does would
give the same numbers (the lab's observation types have no float32 scalar) for four
to ten times the cost of this conversion, a third of a maze tick's. The action is a
float64 ``Box`` over the task's ``Actions`` dimensions: the command messages carry
float64, so every action is exactly what a controller can publish and the bounds are
the task's own (a float32 bound rounded outwards would count a sampled action as
clipped).

**Bad actions.** An action of the wrong shape, or holding NaN or infinity, is a
``ValueError`` naming the dimension (the lab refuses such commands too). A value out of
its dimension's range is clipped, as ``Actions.messages`` does, and counted as the task
counts a clipped command: once per message, in ``task.clipped`` (the metrics'
``clipped_commands``), unless the task counted that message itself.

**Registration.** ``register_all`` registers the environments with Gymnasium; importing
this module calls it. Gymnasium 1.x has no plugin entry points (they were removed in
1.0), so an environment is made either after ``import labd.gym`` or with the module in
its id, which imports it: ``gymnasium.make("labd.gym:labd/icreate-maze-v1")``.

**The raw dm_control environment.** A ``LabTask`` is a dm_control task, so an agent that
prefers dm_control's own interface builds it from the spec:
``spec = labd.sim.registry.get("icreate-maze")``,
``env = spec.build(spec.params.validate({...}), seed)``, a ``control.Environment``.
Its actions are the task's actuator commands (``action_spec``: the maze's two wheel
speeds) and its observations the task's ground truth (``get_observation``), neither of
which a controller has: a policy learnt there does not run as a controller as is.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping, Sequence
from typing import Any, SupportsFloat

import gymnasium
import numpy as np
from gymnasium import spaces

from labd.graph.codec import Codec, codec_for
from labd.graph.types import TypeRegistry
from labd.sim import registry
from labd.sim.base import ObservationTopic, stamp_of
from labd.sim.camera import Camera
from labd.sim.registry import TaskSpec
from labd.sim.simulation import Simulation

NAMESPACE = "labd"
ENTRY_POINT = "labd.gym:LabEnv"
SEEDS = 2**63  # the lab's seeds: 0 .. 2**63 - 1
# Seeds a reset without one draws: 32 bits, which every task takes (pr2-table seeds numpy's
# legacy RandomState with its seed, which refuses more than 32 bits).
DRAWN = 2**32
CAMERA_SIZE = (320, 240)  # a camera's width and height where a task has no such parameters

log = logging.getLogger("labd.gym")


def env_id(spec: TaskSpec) -> str:
    """The Gymnasium id of a task: ``labd/NAME-vVERSION``."""
    return f"{NAMESPACE}/{spec.name}-v{spec.version}"


def learnable(spec: TaskSpec) -> bool:
    """Whether a task can be an environment: a command vector, a layout, a whole version."""
    return spec.actions is not None and spec.layout is not None and spec.version.isdigit()


def register_all() -> list[str]:
    """Register every learnable task with Gymnasium (see the module's docstring); the
    ids, in the registry's order. Registering again changes nothing."""
    ids = []
    for name in registry.names():
        spec = registry.get(name)
        if not learnable(spec):
            log.debug("task %s has no Gymnasium environment", name)
            continue
        made = env_id(spec)
        if made not in gymnasium.registry:
            gymnasium.register(made, entry_point=ENTRY_POINT, kwargs={"task": name})
        ids.append(made)
    return ids


class LabEnv(gymnasium.Env[np.ndarray, np.ndarray]):
    """One learnable task of the lab, stepped in-process (see the module's docstring).

    ``params`` are the task's parameters (``labd tasks`` lists them; ``ParamError`` if
    one is unacceptable); ``render_mode`` is None or ``"rgb_array"`` (the task's camera,
    at its ``camera_width`` x ``camera_height``).

    ``info`` holds the lab's ``seed``, the ``tick``, the episode's ``status`` and
    ``reason`` (as ``/lab/episode`` says them) and the ``metrics`` a trial records.
    ``truncated`` is the time limit (the ``time_limit`` parameter) ending the episode,
    whatever the task's verdict there (``Simulation.truncated``: a dm_control pack task
    judges its return at its time limit, ``status`` succeeded or failed); ``terminated``
    is any other end: the task succeeding or failing before it, a diverging physics.
    """

    # what gymnasium.make reads before making one; each instance narrows it to its task
    metadata: dict[str, Any] = {"render_modes": ["rgb_array"]}  # noqa: RUF012

    def __init__(
        self,
        task: str,
        params: Mapping[str, Any] | None = None,
        render_mode: str | None = None,
    ) -> None:
        spec = registry.get(task)
        if spec.actions is None or spec.layout is None:
            lacks = "actions" if spec.actions is None else "layout"
            raise ValueError(f"the task {task!r} declares no {lacks}: it is no environment")
        self.task_spec = spec
        self.actions = spec.actions
        self.layout = spec.layout
        self.values = spec.params.validate(dict(params or {}))
        dimensions = self.actions.dimensions
        self.action_space = spaces.Box(
            np.array([d.low for d in dimensions]),
            np.array([d.high for d in dimensions]),
            dtype=np.float64,
        )
        self.observation_space = spaces.Box(
            -np.inf, np.inf, (len(self.layout.observation),), dtype=np.float32
        )
        modes = ["rgb_array"] if spec.camera else []
        self.metadata = {"render_modes": modes}
        if "control_rate" in self.values:  # every lab task has it (``base.environment``)
            self.metadata["render_fps"] = int(self.values["control_rate"])
        if render_mode is not None and render_mode not in modes:
            raise ValueError(f"render_mode must be one of {modes} or None, got {render_mode!r}")
        self.render_mode = render_mode
        types = TypeRegistry.shared()
        self._commands: dict[str, Codec] = {
            topic: codec_for(types, kind) for topic, (kind, _) in self.actions.templates.items()
        }
        self._types = types
        self._entries: dict[str, list[int]] = {}
        for i, entry in enumerate(self.layout.observation):
            for topic in entry.topics:
                self._entries.setdefault(topic, []).append(i)
        self._sim: Simulation | None = None
        self._camera: Camera | None = None
        self._observed: tuple[tuple[ObservationTopic, Codec], ...] = ()
        self._latest: dict[str, Any] = {}
        self._state: list[float] = []

    # -- episodes ------------------------------------------------------------------------

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """A new episode: the lab's seed ``seed`` if given, else the next one drawn from
        ``np_random`` (itself seeded by the last ``seed`` given), below ``DRAWN``.
        ``options`` are not used."""
        if seed is not None and not 0 <= seed < SEEDS:
            raise ValueError(f"seed must be between 0 and 2**63 - 1 (the lab's), got {seed}")
        super().reset(seed=seed)
        lab_seed = seed if seed is not None else int(self.np_random.integers(DRAWN))
        self._close_episode()
        sim = self._sim = Simulation(self.task_spec, self.values, lab_seed)
        observed = set(self._entries)
        self._observed = tuple(
            (topic, codec_for(self._types, topic.type))
            for topic in sim.task.observations
            if topic.name in observed
        )
        unknown = observed - {topic.name for topic, _ in self._observed}
        if unknown:
            raise ValueError(
                f"the layout of {self.task_spec.name} reads {', '.join(sorted(unknown))},"
                " which the task does not publish"
            )
        if self.render_mode == "rgb_array" and self.task_spec.camera:
            width, height = CAMERA_SIZE
            width = int(self.values.get("camera_width", width))
            height = int(self.values.get("camera_height", height))
            self._camera = Camera(self.task_spec.camera, "", width, height)
        self._latest = {}
        self._state = [e.neutral for e in self.layout.observation]
        self._observe(sim)
        return self._observation(), self._info(sim)

    def step(
        self, action: np.ndarray
    ) -> tuple[np.ndarray, SupportsFloat, bool, bool, dict[str, Any]]:
        """Publish the commands ``action`` stands for, step one control tick, observe."""
        sim = self._running()
        vector = self._vector(action)
        self._command(sim, vector)
        sim.step()
        self._observe(sim)
        # Gymnasium's convention, dm_control's too (a last discount of 1): an episode its
        # time limit ended is truncated, whatever its status, so an agent bootstraps there
        truncated = sim.truncated
        terminated = not sim.running and not truncated
        return self._observation(), sim.reward, terminated, truncated, self._info(sim)

    def render(self) -> np.ndarray | None:
        """The task's camera now (height x width x 3, uint8) with ``render_mode``
        ``"rgb_array"``; None without a render mode."""
        if self.render_mode is None:
            return None
        sim = self._running()
        assert self._camera is not None
        return np.ascontiguousarray(self._camera.render(sim.physics))

    def close(self) -> None:
        """Free the episode's physics and its rendering (again: nothing happens)."""
        self._close_episode()

    def _close_episode(self) -> None:
        sim, self._sim, self._camera = self._sim, None, None
        if sim is not None:
            sim.close()

    @property
    def simulation(self) -> Simulation:
        """The episode's ``Simulation`` (its ``task``, ``physics``, ``tick``)."""
        return self._running()

    def _running(self) -> Simulation:
        if self._sim is None:
            raise gymnasium.error.ResetNeeded("call reset() before step() or render()")
        return self._sim

    # -- commands ------------------------------------------------------------------------

    def _vector(self, action: Any) -> list[float]:
        """The action as floats, refused unless it has the right shape and is finite."""
        dimensions = self.actions.dimensions
        try:
            values = np.asarray(action, dtype=np.float64)
        except (TypeError, ValueError):
            raise ValueError(
                f"an action of {self.task_spec.name} is {len(dimensions)} numbers,"
                f" got {type(action).__name__}"
            ) from None
        if values.shape != (len(dimensions),):
            raise ValueError(
                f"an action of {self.task_spec.name} is {len(dimensions)} numbers"
                f" ({', '.join(d.name for d in dimensions)}), got shape {values.shape}"
            )
        vector: list[float] = values.tolist()
        for i, (dimension, value) in enumerate(zip(dimensions, vector, strict=True)):
            if not math.isfinite(value):
                raise ValueError(
                    f"action[{i}] ({dimension.name}) must be a finite number, got {value}"
                )
        return vector

    def _command(self, sim: Simulation, vector: Sequence[float]) -> None:
        """Hand the task the messages ``vector`` stands for, as the robot node does."""
        stamp = stamp_of(sim.physics)
        now = (stamp["sec"], stamp["nanosec"])
        beyond = {
            d.topic
            for d, value in zip(self.actions.dimensions, vector, strict=True)
            if not d.low <= value <= d.high
        }
        task = sim.task
        for topic, message in self.actions.messages(vector).items():
            data = self._commands[topic].normalize(message, lambda: now)
            counted = task.clipped.get(topic, 0)
            task.command(topic, data)
            if topic in beyond and task.clipped.get(topic, 0) == counted:
                task.clipped[topic] = counted + 1

    # -- observations --------------------------------------------------------------------

    def _observe(self, sim: Simulation) -> None:
        """This tick's messages of the layout's topics, as the robot publishes them (in
        the task's order, each when its period says), into the observation entries."""
        stamp = stamp_of(sim.physics)
        now = (stamp["sec"], stamp["nanosec"])
        entries = self.layout.observation
        for topic, codec in self._observed:
            due = sim.tick == 0 if topic.period == 0 else sim.tick % topic.period == 0
            if not due:
                continue
            data = sim.task.observe(sim.physics, topic.name, stamp)
            if data is None:
                continue
            self._latest[topic.name] = codec.to_rosbags(codec.normalize(data, lambda: now))
            for i in self._entries[topic.name]:
                value = entries[i].extract(self._latest, topic.name)
                if value is not None:
                    self._state[i] = float(value)

    def _observation(self) -> np.ndarray:
        return np.array(self._state, dtype=np.float32)

    def _info(self, sim: Simulation) -> dict[str, Any]:
        return {
            "seed": sim.seed,
            "tick": sim.tick,
            "status": sim.status.value,
            "reason": sim.reason,
            "metrics": sim.metrics(),
        }


register_all()
