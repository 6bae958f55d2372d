"""One episode of a task: the dm_control environment, its tick count and its outcome.

The step loop is dm_control's own (``control.Environment.step``); this class adds what
the lab needs around it: the action comes from the commands the task has received,
a diverging physics ends the episode as failed instead of raising, and the outcome
says why the episode ended.
"""

from __future__ import annotations

import hashlib
import logging
import mimetypes
from collections.abc import Mapping
from typing import Any

import mujoco
import numpy as np
from dm_control.rl import control

from labd.errors import EpisodeOverError, ParamError
from labd.sim import registry
from labd.sim.base import LabTask
from labd.sim.params import Value
from repository.trial import EpisodeStatus
from repository.well_known import MODEL, MODEL_ASSETS

log = logging.getLogger("labd.sim")


class Simulation:
    """One episode of a registered task, built from its parameters and seed."""

    def __init__(
        self,
        task: str | registry.TaskSpec,
        params: Mapping[str, Any] | None = None,
        seed: int = 0,
        *,
        time_limit: float | None = None,
    ) -> None:
        self.spec = task if isinstance(task, registry.TaskSpec) else registry.get(task)
        self.values: dict[str, Value] = self.spec.params.validate(params or {})
        if not 0 <= seed < 2**63:
            raise ParamError("seed", f"must be between 0 and 2**63 - 1, got {seed}")
        self.seed = seed
        kwargs = {} if time_limit is None else {"time_limit": time_limit}
        self.env: control.Environment = self.spec.build(self.values, seed, **kwargs)
        task_obj = self.env.task
        assert isinstance(task_obj, LabTask)
        self.task: LabTask = task_obj
        self.tick = 0
        self.diverged = False  # the physics blew up (a failure of the lab's model, not the task)
        # the time limit ended the episode, whatever its status says (Gymnasium's truncated)
        self.truncated = False
        self.status = EpisodeStatus.RUNNING
        self.reason = ""
        self.reward = 0.0  # of the last tick
        self.total_reward = 0.0
        self.env.reset()

    @property
    def physics(self) -> Any:
        return self.env.physics

    @property
    def control_timestep(self) -> float:
        return float(self.env.control_timestep())

    @property
    def time_ns(self) -> int:
        return round(float(self.physics.data.time) * 1e9)

    @property
    def running(self) -> bool:
        return self.status is EpisodeStatus.RUNNING

    def step(self) -> None:
        """Advance one control tick with the action the commands so far call for."""
        if not self.running:
            raise EpisodeOverError(self.status, self.reason)
        action = self.task.action(self.physics)
        try:
            timestep = self.env.step(action)
        except control.PhysicsError as err:
            self.tick += 1
            self.diverged = True
            self._end(EpisodeStatus.FAILED, f"the physics diverged at tick {self.tick}: {err}")
            return
        self.tick += 1
        self.reward = float(timestep.reward or 0.0)
        self.total_reward += self.reward
        if timestep.last():
            outcome = self.task.outcome(self.physics)
            if outcome is not None:
                self.truncated = outcome.truncated
                self._end(outcome.status, outcome.reason)
            else:
                self.truncated = True
                limit = self.tick * self.control_timestep
                self._end(EpisodeStatus.TRUNCATED, f"the time limit of {limit:g} s was reached")

    def _end(self, status: EpisodeStatus, reason: str) -> None:
        self.status = status
        self.reason = reason
        log.info(
            "%s seed %d: %s at tick %d: %s", self.spec.name, self.seed, status, self.tick, reason
        )

    def metrics(self) -> dict[str, bool | int | float]:
        """The task's figures, with the episode's own (ticks, time, total reward)."""
        figures = dict(self.task.metrics(self.physics))
        figures.setdefault("success", self.status is EpisodeStatus.SUCCEEDED)
        figures["ticks"] = self.tick
        figures["time"] = self.time_ns / 1e9
        figures["total_reward"] = self.total_reward
        return figures

    def model_digest(self) -> str:
        """sha256 of the compiled model (MJB), which names the physics exactly."""
        model = self.physics.model.ptr
        buffer = np.zeros(mujoco.mj_sizeModel(model), dtype=np.uint8)
        mujoco.mj_saveModel(model, None, buffer)
        return hashlib.sha256(buffer.tobytes()).hexdigest()

    def model_xml(self) -> str:
        """The model as MJCF, for the record (what was compiled, not the generator)."""
        return self.task.model_xml

    def model_files(self) -> dict[str, tuple[str, bytes]]:
        """The model as a record's attachments: ``model.xml`` and the files it names
        (``model/NAME``: textures), so that MuJoCo compiles it back from the record."""
        files = {MODEL: ("application/xml", self.model_xml().encode())}
        for name, data in self.task.model_assets.items():
            kind = mimetypes.guess_type(name)[0] or "application/octet-stream"
            files[MODEL_ASSETS + name] = (kind, data)  # image/png, ...
        return files

    def close(self) -> None:
        """Free the physics and its rendering contexts, on the thread that made them.

        EGL contexts left to the garbage collector may be destroyed on another thread,
        which fails; a simulation that rendered should be closed where it rendered.
        """
        self.physics.free()

    def __repr__(self) -> str:
        state = self.status if self.reason == "" else f"{self.status}: {self.reason}"
        return f"Simulation({self.spec.name}, seed={self.seed}, tick={self.tick}, {state})"
