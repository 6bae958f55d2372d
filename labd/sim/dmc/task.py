"""The pack's ``LabTask``: a dm_control suite task, unchanged, with the lab's ROS face.

``SuiteTask.make`` builds an episode with ``dm_control.suite.load(domain, task,
task_kwargs={"random": seed})`` and keeps the suite's own task object inside a
``SuiteTask``, which hands every dm_control call (``initialize_episode``,
``before_step``, ``after_step``, the reward, the observation, the termination and the
specs) to it. The environment around them is a ``control.Environment`` on the suite's
own physics with the suite's own number of physics steps per tick and episode length.
So one lab tick is one step of the suite's environment, and the same actions give the
same rewards and observations, bit for bit, as the suite's environment with that seed.

The wrapper draws no random numbers: its ``random`` is the suite task's generator,
which only the suite task uses.

The ROS side (docs/tasks.md, "The dm_control suite pack"):

- ``/action`` (``std_msgs/msg/Float64MultiArray``): the action, one value per actuator
  in the action spec's order. A message of the wrong length or with a NaN or infinity
  is refused (``MessageError``) and changes nothing; values out of the spec's bounds are
  clipped, and the message counts once in ``clipped``. It holds until replaced; before
  any, the action is zeros (the **neutral** action: no actuator pushes).
- ``/observation/KEY`` (``std_msgs/msg/Float64MultiArray``) for each key of the suite's
  observation, flattened in C order, with its shape in ``layout.dim``; ``/reward``
  (``std_msgs/msg/Float64``) of the last tick; ``/joint_states``, ``/tf`` (every body in
  ``world``) and the suite's default camera (camera 0).
- The episode ends where the suite's does (its step limit, or its own termination), or
  at the lab's ``time_limit`` if that is shorter: it succeeded if its return reached the
  task's threshold (``Listing.threshold``), and failed otherwise. Ended by its time
  limit, it is also truncated (``Outcome.truncated``): the suite's task would go on, as
  dm_control's last discount of 1 says, so Gymnasium is told ``truncated``, not
  ``terminated``. ``/lab/episode`` keeps the verdict as its status, as every record of
  the pack has it, so those records still replay and their reruns still reproduce.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from collections.abc import Callable, Mapping
from typing import Any, ClassVar

import mujoco
import numpy as np
from dm_control import suite
from dm_control.rl import control
from dm_control.suite import common

from labd.errors import MessageError
from labd.sim.base import (
    LARGEST_SEED,
    CommandTopic,
    LabTask,
    ObservationTopic,
    Outcome,
    Stamp,
    finite,
    random_state,
)
from labd.sim.camera import Camera
from labd.sim.dmc.catalog import Listing
from labd.sim.params import Param, Params, Value
from labd.sim.registry import Actions, Dimension
from repository.trial import EpisodeStatus

VERSION = "1"
ACTION = "/action"
REWARD = "/reward"
OBSERVATION = "/observation/"  # + the observation's key
JOINT_STATES = "/joint_states"
TF = "/tf"
CAMERA_INFO = "/camera/camera_info"
CAMERA_IMAGE = "/camera/image/compressed"
CAMERA_RATE = 25  # frames a second at most, in simulation time
ARRAY = "std_msgs/msg/Float64MultiArray"
WORLD = "world"
OPTICAL_FRAME = "camera_optical_frame"
# MuJoCo's camera frame (x right, y up, looking down -z) to ROS's optical (z ahead, y down)
TO_OPTICAL = np.diag([1.0, -1.0, -1.0])
MOVING_JOINTS = (int(mujoco.mjtJoint.mjJNT_SLIDE), int(mujoco.mjtJoint.mjJNT_HINGE))


def random_for(seed: int) -> int | np.random.RandomState:
    """What the suite's ``random`` gets for a lab seed: the seed itself where numpy's
    ``RandomState`` takes it (0 to 2**32 - 1, so ``suite.load`` with that seed is the same
    episode), else a generator seeded with its two 32-bit halves (held-out suites draw
    63-bit seeds)."""
    return seed if seed <= LARGEST_SEED else random_state(seed)


def params_of(listing: Listing) -> Params:
    """A pack task's parameters: the episode's length and the camera's size."""
    return Params(
        [
            Param(
                "time_limit",
                listing.time_limit,
                f"seconds of simulation time before the episode ends; at most the suite's own "
                f"{listing.time_limit:g} s (its returns, and the threshold, are for that length)",
                minimum=listing.control_timestep,
                maximum=listing.time_limit,
            ),
            Param("camera_width", 320, "camera image width, pixels", 16, 640),
            Param("camera_height", 240, "camera image height, pixels", 16, 480),
        ]
    )


def model_of(listing: Listing) -> tuple[str, dict[str, bytes]]:
    """The MJCF and the files it includes, as the suite's factory for the task compiles
    them (for the trial record; the tests hold it to the suite's compiled model)."""
    module = getattr(suite, listing.domain)
    if listing.domain == "swimmer":  # swimmer6: six links, five joints
        xml, assets = module.get_model_and_assets(int(listing.task.removeprefix("swimmer")))
    elif listing.domain == "quadruped":  # the floor is as long as the run at full speed
        speed = {"walk": module._WALK_SPEED, "run": module._RUN_SPEED}[listing.task]
        xml, assets = (
            module.make_model(floor_size=module._DEFAULT_TIME_LIMIT * speed),
            common.ASSETS,
        )
    else:
        xml, assets = module.get_model_and_assets()
    text = xml.decode() if isinstance(xml, bytes) else str(xml)
    return text, dict(assets)


def array_message(value: np.ndarray) -> dict[str, Any]:
    """std_msgs/msg/Float64MultiArray: ``value`` flattened in C order, its shape in the
    layout (one dimension per axis, ``stride`` the size of the block below it)."""
    shape = value.shape
    dims = [
        {"label": "", "size": int(size), "stride": int(math.prod(shape[axis:]))}
        for axis, size in enumerate(shape)
    ]
    data = np.asarray(value, dtype=np.float64).ravel().tolist()
    return {"layout": {"dim": dims, "data_offset": 0}, "data": data}


def _quaternion(rotation: np.ndarray) -> dict[str, float]:
    """A rotation matrix as a geometry_msgs/Quaternion, the one with w >= 0."""
    quat = np.zeros(4)
    mujoco.mju_mat2Quat(quat, np.ascontiguousarray(rotation).reshape(9))
    w, x, y, z = (float(v) for v in (quat if quat[0] >= 0 else -quat))
    return {"x": x, "y": y, "z": z, "w": w}


def _vector(v: np.ndarray) -> dict[str, float]:
    return {"x": float(v[0]), "y": float(v[1]), "z": float(v[2])}


class SuiteTask(LabTask):
    """A task of ``dm_control.suite`` as a lab task. One subclass per pack task
    (``task_class``) carries its name, topics and parameters for the registry."""

    listing: ClassVar[Listing]

    def __init__(self, params: Mapping[str, Value], inner: Any, physics: Any) -> None:
        super().__init__(params, inner.random)  # the suite task's generator, never drawn here
        self.inner = inner  # the suite's own task object
        spec = inner.action_spec(physics)
        self.minimum = np.broadcast_to(np.asarray(spec.minimum, np.float64), spec.shape).copy()
        self.maximum = np.broadcast_to(np.asarray(spec.maximum, np.float64), spec.shape).copy()
        self.step_limit = math.inf  # the environment's, in steps (``make`` sets it)
        self.camera = Camera(
            self.listing.camera,
            OPTICAL_FRAME,
            int(params["camera_width"]),
            int(params["camera_height"]),
        )
        model = physics.model
        joints = [
            j
            for j in range(model.njnt)
            if int(model.jnt_type[j]) in MOVING_JOINTS and model.joint(j).name
        ]
        self.joint_names = [model.joint(j).name for j in joints]
        self.joint_qpos = np.array([int(model.jnt_qposadr[j]) for j in joints], dtype=int)
        self.joint_dofs = np.array([int(model.jnt_dofadr[j]) for j in joints], dtype=int)
        self.bodies = [(b, model.body(b).name) for b in range(1, model.nbody) if model.body(b).name]
        self._observers: dict[str, Callable[[Any, Stamp], dict[str, Any]]] = {
            REWARD: lambda physics, stamp: {"data": float(self.reward)},
            JOINT_STATES: self._joint_states,
            TF: self._transforms,
            CAMERA_INFO: self.camera.info,
            CAMERA_IMAGE: self.camera.image,
        }
        self._reset()

    def _reset(self) -> None:
        self.held = np.zeros(self.minimum.shape)  # the neutral action
        self.steps = 0
        self.reward: Any = 0.0  # the last step's, as the suite computed it
        self.total_reward = 0.0
        self.terminated = False  # the suite's own termination ended the episode
        self.observation: OrderedDict[str, np.ndarray] | None = None  # the newest step's

    @classmethod
    def make(
        cls, values: Mapping[str, Value], seed: int, *, time_limit: float | None = None
    ) -> control.Environment:
        """One episode: the suite's environment for ``seed``, its task wrapped in this class.

        ``time_limit`` (seconds) overrides the parameter (``inf`` for live robots)."""
        listing = cls.listing
        loaded = suite.load(listing.domain, listing.task, task_kwargs={"random": random_for(seed)})
        task = cls(values, loaded.task, loaded.physics)
        task.model_xml, task.model_assets = model_of(listing)
        limit = float(values["time_limit"]) if time_limit is None else time_limit
        # The suite's own physics steps per tick (private in dm_control: no accessor).
        env = control.Environment(
            loaded.physics, task, time_limit=limit, n_sub_steps=loaded._n_sub_steps
        )
        task.step_limit = env._step_limit
        return env

    # -- dm_control: the suite's task decides ----------------------------------------

    def initialize_episode(self, physics: Any) -> None:
        """The suite's own start. (No ``super()``: the suite task runs its own.)"""
        self.inner.initialize_episode(physics)
        self._reset()

    def before_step(self, action: np.ndarray, physics: Any) -> None:
        self.inner.before_step(action, physics)

    def after_step(self, physics: Any) -> None:
        """The suite's after-step, then this step's reward (the suite's rewards depend on
        the state only, so computing it here is computing it where dm_control does)."""
        self.inner.after_step(physics)
        self.reward = self.inner.get_reward(physics)
        self.steps += 1
        self.total_reward += float(self.reward)

    def get_reward(self, physics: Any) -> Any:
        return self.reward

    def get_observation(self, physics: Any) -> OrderedDict[str, np.ndarray]:
        """The suite's observation, each value an array (a 0-d one for a scalar)."""
        observation = self.inner.get_observation(physics)
        self.observation = OrderedDict((k, np.asarray(v)) for k, v in observation.items())
        return self.observation

    def get_termination(self, physics: Any) -> Any:
        discount = self.inner.get_termination(physics)
        if discount is not None:
            self.terminated = True
        return discount

    def action_spec(self, physics: Any) -> Any:
        return self.inner.action_spec(physics)

    def observation_spec(self, physics: Any) -> Any:
        return self.inner.observation_spec(physics)

    # -- the ROS side ------------------------------------------------------------------

    def command(self, topic: str, data: dict[str, Any]) -> None:
        """Keep an ``/action``: its length and numbers checked, then clipped to the spec."""
        if topic != ACTION:
            raise MessageError(f"is not a command topic of {self.name}", [topic])
        values = data["data"]
        size = len(self.minimum)
        if len(values) != size:
            actuators = ", ".join(self.listing.actuators)
            raise MessageError(
                f"must hold {size} value{'s' if size > 1 else ''}, one per actuator "
                f"({actuators}), got {len(values)}",
                ["data"],
            )
        action = np.array([finite(float(v), "data", i) for i, v in enumerate(values)])
        clipped = np.clip(action, self.minimum, self.maximum)
        if np.any(clipped != action):
            self.clipped[topic] = self.clipped.get(topic, 0) + 1
        self.held = clipped

    def action(self, physics: Any) -> np.ndarray:
        return self.held.copy()

    def observe(self, physics: Any, topic: str, stamp: Stamp) -> dict[str, Any] | None:
        if topic.startswith(OBSERVATION):
            observation = self.observation
            if observation is None:  # before the environment's first reset
                observation = self.get_observation(physics)
            return array_message(observation[topic[len(OBSERVATION) :]])
        return self._observers[topic](physics, stamp)

    def _joint_states(self, physics: Any, stamp: Stamp) -> dict[str, Any]:
        """sensor_msgs/JointState: every named hinge and slide joint (rad or m), its speed,
        and the actuators' force on it (N m or N)."""
        data = physics.data
        return {
            "header": {"stamp": stamp, "frame_id": ""},
            "name": list(self.joint_names),
            "position": data.qpos[self.joint_qpos].tolist(),
            "velocity": data.qvel[self.joint_dofs].tolist(),
            "effort": data.qfrc_actuator[self.joint_dofs].tolist(),
        }

    def _transforms(self, physics: Any, stamp: Stamp) -> dict[str, Any]:
        """tf2_msgs/TFMessage: every named body, and the camera's optical frame, in world."""
        data = physics.data
        header = {"stamp": stamp, "frame_id": WORLD}
        out = []
        for b, name in self.bodies:
            w, x, y, z = (float(v) for v in data.xquat[b])
            out.append(
                {
                    "header": header,
                    "child_frame_id": name,
                    "transform": {
                        "translation": _vector(data.xpos[b]),
                        "rotation": {"x": x, "y": y, "z": z, "w": w},
                    },
                }
            )
        camera = self.listing.camera
        rotation = physics.named.data.cam_xmat[camera].reshape(3, 3) @ TO_OPTICAL
        out.append(
            {
                "header": header,
                "child_frame_id": OPTICAL_FRAME,
                "transform": {
                    "translation": _vector(physics.named.data.cam_xpos[camera]),
                    "rotation": _quaternion(rotation),
                },
            }
        )
        return {"transforms": out}

    def outcome(self, physics: Any) -> Outcome | None:
        """None until the episode's last step; then success if the return reached the
        threshold, truncated unless the suite's own termination ended it."""
        if not (self.terminated or self.steps >= self.step_limit):
            return None
        truncated = not self.terminated
        threshold = self.listing.threshold
        ended = (
            f"the suite ended the episode at step {self.steps}"
            if self.terminated
            else f"after {self.steps} steps ({self.steps * self.listing.control_timestep:g} s)"
        )
        if self.total_reward >= threshold:
            return Outcome(
                EpisodeStatus.SUCCEEDED,
                f"the return {self.total_reward:.1f} reached the threshold {threshold:g} {ended}",
                truncated,
            )
        short = ""
        if not self.terminated and self.steps < self.listing.steps:
            short = f"; the suite's episode is {self.listing.steps} steps, this one was cut short"
        return Outcome(
            EpisodeStatus.FAILED,
            f"the return {self.total_reward:.1f} fell short of the threshold {threshold:g} "
            f"{ended}{short}",
            truncated,
        )

    def metrics(self, physics: Any) -> dict[str, bool | int | float]:
        """``reward`` is the return so far (the suite's sum of rewards); ``success``
        whether it reached ``return_threshold``."""
        return {
            "success": self.total_reward >= self.listing.threshold,
            "reward": self.total_reward,
            "return_threshold": self.listing.threshold,
            "steps": self.steps,
            "clipped_commands": sum(self.clipped.values()),
        }


def task_class(listing: Listing) -> type[SuiteTask]:
    """The ``SuiteTask`` subclass of one pack task: its name, parameters and topics as
    class attributes, known without building an episode. Its camera shows at most
    ``CAMERA_RATE`` frames a second: a 100 Hz task rendered every tick would take more
    than a core live."""
    frames = max(1, round(1 / (CAMERA_RATE * listing.control_timestep)))
    observations = [
        ObservationTopic(
            OBSERVATION + key,
            ARRAY,
            f"the suite's observation {key!r} ({'x'.join(map(str, shape)) or 'scalar'}), flat",
        )
        for key, shape in listing.observations
    ]
    observations += [
        ObservationTopic(REWARD, "std_msgs/msg/Float64", "the last tick's reward, 0 to 1"),
        ObservationTopic(JOINT_STATES, "sensor_msgs/msg/JointState", "hinge and slide joints"),
        ObservationTopic(TF, "tf2_msgs/msg/TFMessage", "every body in world"),
        ObservationTopic(CAMERA_INFO, "sensor_msgs/msg/CameraInfo", "intrinsics"),
        ObservationTopic(
            CAMERA_IMAGE,
            "sensor_msgs/msg/CompressedImage",
            f"the suite's camera {listing.camera!r}, JPEG, every {frames} ticks"
            if frames > 1
            else f"the suite's camera {listing.camera!r}, JPEG",
            period=frames,
            on_demand=True,
        ),
    ]
    commands = (
        CommandTopic(
            ACTION,
            ARRAY,
            f"{listing.action_size} values within the action spec's bounds, one per actuator "
            f"({', '.join(listing.actuators)}); held until replaced; zeros before any",
        ),
    )
    title = "".join(part.capitalize() for part in f"{listing.domain}_{listing.task}".split("_"))
    attributes = {
        "__doc__": f"dm_control's {listing.domain} {listing.task}: {listing.goal}.",
        "__module__": __name__,
        "name": listing.name,
        "version": VERSION,
        "params": params_of(listing),
        "commands": commands,
        "observations": tuple(observations),
        "listing": listing,
    }
    made = type(f"Dmc{title}", (SuiteTask,), attributes)
    assert issubclass(made, SuiteTask)
    return made


def actions_of(listing: Listing) -> Actions:
    """A pack task's commands as a vector: one dimension per actuator, each a value of
    ``/action``'s ``data``, within the actuator's bounds, 0 before any command."""
    size = listing.action_size
    template = {"layout": {"dim": [], "data_offset": 0}, "data": [0.0] * size}
    return Actions(
        dimensions=tuple(
            Dimension(name, ACTION, f"data.{i}", low, high)
            for i, (name, (low, high)) in enumerate(
                zip(listing.actuators, listing.bounds, strict=True)
            )
        ),
        templates={ACTION: (ARRAY, template)},
    )
