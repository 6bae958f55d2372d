"""dm_control's soccer (``dm_control.locomotion.soccer``) as lab tasks: two teams of
BoxHead walkers on a randomized pitch, unchanged, with the lab's ROS face.

``SoccerTask.make`` builds an episode with ``soccer.load(team_size, time_limit,
random_state=seed, walker_type=BOXHEAD, terminate_on_goal=True)``. dm_control's soccer
is a composer environment (its own step loop, per-player actions, observations and
rewards), so the lab's step loop drives it through ``MatchEnvironment``, which looks
like the ``control.Environment`` the other tasks build: one lab tick is one step of the
soccer environment (0.025 s of simulation, its 5 physics steps), and the same actions
give the same observations, bit for bit, as dm_control's own environment for the seed.
The wrapper draws no random numbers of its own.

The ROS side (docs/tasks.md, "Soccer"): every topic of a team is under its side,
``/home`` or ``/away``, so that a match can give each team's session its own side as
``/`` (matches are still to come: issue 36), and one record holds both teams' topics:

- ``/SIDE/player_I/action`` (``std_msgs/msg/Float64MultiArray``): the walker's three
  values, roll, steer and kick, each clipped to [-1, 1] (a message that needed it counts
  once in ``clipped``); NaN, infinity or a wrong length are refused and change nothing.
  A command holds until replaced; before any, the player stands still (zeros).
- ``/SIDE/player_I/observation/KEY`` (the same type, flattened) for each key dm_control
  gives that player: ego-centric and team-relative (``ball_ego_position``,
  ``team_goal_mid``, ``opponent_0_ego_position``, ``stats_home_score`` is 1 on the step
  the player's own team scores).
- ``/SIDE/score`` (``std_msgs/msg/Int32MultiArray``): ``[ours, theirs]``, the goals so far.
- ``/camera/image/compressed``: the pitch from above (``top_down``), on demand.

An episode (a leg of a match) ends at the first goal or at its time limit. From the
home side's view, the one a lone controller plays (against an away team that stands
still, its commands never sent): it succeeded if home scored, and failed if away
scored or nobody did by the time limit (then also truncated: the game would go on).
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Mapping, Sequence
from typing import Any, ClassVar

import dm_env
import numpy as np
from dm_control.locomotion import soccer
from dm_env import specs

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
from labd.sim.dmc.task import array_message
from labd.sim.params import Param, Params, Value
from labd.sim.registry import Actions, Dimension
from repository.trial import EpisodeStatus

VERSION = "1"
SIDES = ("home", "away")
ARRAY = "std_msgs/msg/Float64MultiArray"
SCORE_TYPE = "std_msgs/msg/Int32MultiArray"
ACTUATORS = ("roll", "steer", "kick")  # a BoxHead walker's action, each in [-1, 1]
CONTROL_TIMESTEP = 0.025  # dm_control's soccer: 40 ticks a second, 5 physics steps each
TIME_LIMIT = 45.0  # seconds of a leg, dm_control's own default
LONGEST = 300.0
CAMERA = "top_down"
CAMERA_INFO = "/camera/camera_info"
CAMERA_IMAGE = "/camera/image/compressed"
CAMERA_EVERY = 2  # ticks between frames: 20 a second
OPTICAL_FRAME = "camera_optical_frame"

# What dm_control observes for each player (its shape, the leading player axis
# dropped); ``OTHER`` for each teammate and each opponent, named ``teammate_J_`` and
# ``opponent_J_``. tests/labd/sim/test_soccer.py holds this to dm_control's own.
OWN: tuple[tuple[str, tuple[int, ...]], ...] = (
    ("body_height", ()),
    ("end_effectors_pos", (3,)),
    ("joints_pos", (1,)),
    ("joints_vel", (1,)),
    ("prev_action", (3,)),
    ("sensors_accelerometer", (3,)),
    ("sensors_gyro", (3,)),
    ("sensors_velocimeter", (3,)),
    ("world_zaxis", (3,)),
    ("ball_ego_angular_velocity", (3,)),
    ("ball_ego_position", (3,)),
    ("ball_ego_linear_velocity", (3,)),
    ("team_goal_back_right", (2,)),
    ("team_goal_mid", (3,)),
    ("team_goal_front_left", (2,)),
    ("field_front_left", (2,)),
    ("opponent_goal_back_left", (2,)),
    ("opponent_goal_mid", (3,)),
    ("opponent_goal_front_right", (2,)),
    ("field_back_right", (2,)),
    ("stats_vel_to_ball", ()),
    ("stats_closest_vel_to_ball", ()),
    ("stats_veloc_forward", ()),
    ("stats_vel_ball_to_goal", ()),
    ("stats_home_avg_teammate_dist", ()),
    ("stats_teammate_spread_out", ()),
    ("stats_home_score", ()),
    ("stats_away_score", ()),
)
OTHER: tuple[tuple[str, tuple[int, ...]], ...] = (
    ("ego_end_effectors_pos", (3,)),
    ("ego_linear_velocity", (3,)),
    ("ego_position", (3,)),
    ("ego_orientation", (9,)),
    ("end_effectors_pos", (3,)),
)


def player(side: str, index: int) -> str:
    """The topic prefix of player ``index`` of ``side``: ``/home/player_0/``."""
    return f"/{side}/player_{index}/"


def observation_keys(team_size: int) -> list[tuple[str, tuple[int, ...]]]:
    """Each key a player observes in a match of ``team_size`` a side, with its shape,
    in dm_control's order for a home player (an away player's lists its opponents, home's
    players, before its teammates)."""
    keys = [key for key in OWN if key[0] in _BEFORE_OTHERS]
    for role, count in (("teammate", team_size - 1), ("opponent", team_size)):
        for j in range(count):
            keys += [(f"{role}_{j}_{name}", shape) for name, shape in OTHER]
    keys += [key for key in OWN if key[0] not in _BEFORE_OTHERS]
    return keys


# dm_control lists a player's own and the ball's keys, then the others', then the
# pitch's and the statistics
_BEFORE_OTHERS = frozenset(name for name, _ in OWN[:12])


class MatchEnvironment(dm_env.Environment):  # type: ignore[misc]
    """dm_control's composer environment for soccer, stepped as the lab steps a
    ``control.Environment``: ``step`` takes every player's action as one vector (home's
    players, then away's, three values each); the observation is every player's, keyed
    ``/SIDE/player_I/KEY``; the reward is what home scored this step (1, -1 or 0)."""

    def __init__(self, inner: Any, task: SoccerTask) -> None:
        self.inner = inner
        self.task = task

    @property
    def physics(self) -> Any:
        return self.inner.physics

    def control_timestep(self) -> float:
        return float(self.inner.control_timestep())

    def reset(self) -> dm_env.TimeStep:
        """Start the leg: dm_control draws the pitch and the players' places for the seed
        (compiling the episode's model, which the record keeps)."""
        timestep = self.inner.reset()
        model = self.inner.task.root_entity.mjcf_model
        self.task.model_xml = model.to_xml_string()
        self.task.model_assets = dict(model.get_assets())
        self.task.begin(timestep.observation)
        return dm_env.restart(self.task.get_observation(self.physics))

    def step(self, action: np.ndarray) -> dm_env.TimeStep:
        actions = list(np.asarray(action, np.float64).reshape(-1, len(ACTUATORS)))
        timestep = self.inner.step(actions)
        scored = self.inner.task.arena.detected_goal()
        self.task.stepped(timestep.observation, scored)
        reward = 0.0 if scored is None else (1.0 if scored.name == "HOME" else -1.0)
        observation = self.task.get_observation(self.physics)
        if not timestep.last():
            return dm_env.transition(reward, observation)
        if scored is None:  # the time limit: the game would go on
            return dm_env.truncation(reward, observation)
        return dm_env.termination(reward, observation)

    def action_spec(self) -> specs.BoundedArray:
        return self.task.action_spec(self.physics)

    def observation_spec(self) -> OrderedDict[str, specs.Array]:
        return OrderedDict(
            (f"{player(side, i)}{key}", specs.Array(shape, np.float64, name=key))
            for side in SIDES
            for i in range(self.task.team_size)
            for key, shape in self.task.keys
        )

    def reward_spec(self) -> specs.Array:
        return specs.Array((), np.float64, name="reward")

    def discount_spec(self) -> specs.BoundedArray:
        return specs.BoundedArray((), np.float64, 0.0, 1.0, name="discount")


class SoccerTask(LabTask):
    """A soccer match as a lab task: the commands it holds and the observations it
    publishes for both sides. One subclass per team size (``task_class``)."""

    team_size: ClassVar[int]

    def __init__(self, params: Mapping[str, Value], seed: int) -> None:
        super().__init__(params, random_state(seed))  # never drawn: dm_control draws its own
        players = 2 * self.team_size
        self.held = np.zeros((players, len(ACTUATORS)))  # everyone still
        self.slots = {  # each player's action topic -> its row of ``held``
            f"{player(side, i)}action": k * self.team_size + i
            for k, side in enumerate(SIDES)
            for i in range(self.team_size)
        }
        self.keys = observation_keys(self.team_size)
        self.observations_now: list[dict[str, np.ndarray]] = []
        self.goals = {"home": 0, "away": 0}
        self.steps = 0
        self.time_limit = float(params["time_limit"])
        self.scored_at: float | None = None
        self.camera = Camera(
            CAMERA, OPTICAL_FRAME, int(params["camera_width"]), int(params["camera_height"])
        )

    @classmethod
    def make(
        cls, values: Mapping[str, Value], seed: int, *, time_limit: float | None = None
    ) -> MatchEnvironment:
        """One leg: dm_control's soccer for ``seed``, its time limit the parameter's
        (``time_limit`` overrides it: ``inf`` for a live pitch)."""
        limit = float(values["time_limit"]) if time_limit is None else time_limit
        inner = soccer.load(
            team_size=cls.team_size,
            time_limit=limit,
            random_state=seed if seed <= LARGEST_SEED else random_state(seed),
            disable_walker_contacts=False,
            enable_field_box=True,
            terminate_on_goal=True,
            walker_type=soccer.WalkerType.BOXHEAD,
        )
        task = cls({**values, "time_limit": limit}, seed)
        return MatchEnvironment(inner, task)

    # -- what the environment gave back ----------------------------------------------

    def begin(self, observations: Sequence[Mapping[str, np.ndarray]]) -> None:
        self.observations_now = [self._flat(o) for o in observations]

    def stepped(self, observations: Sequence[Mapping[str, np.ndarray]], scored: Any) -> None:
        self.steps += 1
        self.observations_now = [self._flat(o) for o in observations]
        if scored is not None:
            self.goals[scored.name.lower()] += 1
            self.scored_at = self.steps * CONTROL_TIMESTEP

    @staticmethod
    def _flat(observation: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
        """A player's observation without its leading axis (of one player)."""
        return {key: np.asarray(value)[0] for key, value in observation.items()}

    # -- dm_control's Task, as far as anything asks -------------------------------------

    def initialize_episode(self, physics: Any) -> None:
        return None  # dm_control's soccer task starts the leg (``MatchEnvironment.reset``)

    def get_observation(self, physics: Any) -> OrderedDict[str, np.ndarray]:
        return OrderedDict(
            (f"{player(side, i)}{key}", np.asarray(self._player(side, i)[key], np.float64))
            for side in SIDES
            for i in range(self.team_size)
            for key, _ in self.keys
        )

    def get_reward(self, physics: Any) -> float:
        return float(self.goals["home"] - self.goals["away"])

    def action_spec(self, physics: Any) -> specs.BoundedArray:
        players = 2 * self.team_size
        return specs.BoundedArray(
            (players * len(ACTUATORS),), np.float64, -1.0, 1.0, name="\t".join(ACTUATORS)
        )

    # -- the ROS side ------------------------------------------------------------------

    def _player(self, side: str, index: int) -> dict[str, np.ndarray]:
        return self.observations_now[SIDES.index(side) * self.team_size + index]

    def command(self, topic: str, data: dict[str, Any]) -> None:
        """Keep a player's action: three finite numbers, clipped to [-1, 1]."""
        slot = self.slots.get(topic)
        if slot is None:
            raise MessageError(f"is not a command topic of {self.name}", [topic])
        values = data["data"]
        if len(values) != len(ACTUATORS):
            raise MessageError(
                f"must hold 3 values ({', '.join(ACTUATORS)}), got {len(values)}", ["data"]
            )
        action = np.array([finite(float(v), "data", i) for i, v in enumerate(values)])
        clipped = np.clip(action, -1.0, 1.0)
        if np.any(clipped != action):
            self.clipped[topic] = self.clipped.get(topic, 0) + 1
        self.held[slot] = clipped

    def action(self, physics: Any) -> np.ndarray:
        return self.held.reshape(-1).copy()

    def observe(self, physics: Any, topic: str, stamp: Stamp) -> dict[str, Any] | None:
        if topic == CAMERA_IMAGE:
            return self.camera.image(physics, stamp)
        if topic == CAMERA_INFO:
            return self.camera.info(physics, stamp)
        side, _, rest = topic[1:].partition("/")
        if rest == "score":
            other = SIDES[1 - SIDES.index(side)]
            ours, theirs = self.goals[side], self.goals[other]
            return {"layout": {"dim": [], "data_offset": 0}, "data": [ours, theirs]}
        who, _, key = rest.partition("/observation/")
        return array_message(self._player(side, int(who.removeprefix("player_")))[key])

    def outcome(self, physics: Any) -> Outcome | None:
        """How the leg ended (asked at its last step): at a goal, success if home scored;
        at the time limit with no goal, failed and truncated. None while it runs."""
        home, away = self.goals["home"], self.goals["away"]
        score = f"{home}-{away}"
        if self.scored_at is not None:
            if home > away:
                return Outcome(
                    EpisodeStatus.SUCCEEDED, f"home scored at {self.scored_at:g} s: {score}"
                )
            return Outcome(EpisodeStatus.FAILED, f"away scored at {self.scored_at:g} s: {score}")
        if self.steps * CONTROL_TIMESTEP >= self.time_limit - 1e-9:
            played = self.steps * CONTROL_TIMESTEP
            return Outcome(EpisodeStatus.FAILED, f"no goal in {played:g} s: {score}", True)
        return None

    def metrics(self, physics: Any) -> dict[str, bool | int | float]:
        """``reward`` is home's goals less away's; ``success`` whether home won."""
        home, away = self.goals["home"], self.goals["away"]
        return {
            "success": home > away,
            "reward": float(home - away),
            "home_goals": home,
            "away_goals": away,
            "steps": self.steps,
            "clipped_commands": sum(self.clipped.values()),
        }


def task_class(team_size: int) -> type[SoccerTask]:
    """The ``SoccerTask`` of ``team_size`` players a side: its name, parameters and
    topics as class attributes, known without building a leg."""
    name = f"soccer-{team_size}v{team_size}"
    observations: list[ObservationTopic] = []
    commands: list[CommandTopic] = []
    for side in SIDES:
        for i in range(team_size):
            prefix = player(side, i)
            commands.append(
                CommandTopic(
                    prefix + "action",
                    ARRAY,
                    f"{side}'s player {i}: roll, steer, kick, each in [-1, 1]; held until "
                    "replaced; zeros (standing still) before any",
                )
            )
            observations += [
                ObservationTopic(
                    f"{prefix}observation/{key}",
                    ARRAY,
                    f"{side}'s player {i}: dm_control's {key!r} "
                    f"({'x'.join(map(str, shape)) or 'scalar'}), flat",
                )
                for key, shape in observation_keys(team_size)
            ]
        observations.append(
            ObservationTopic(f"/{side}/score", SCORE_TYPE, f"{side}'s goals, then the other's")
        )
    observations += [
        ObservationTopic(CAMERA_INFO, "sensor_msgs/msg/CameraInfo", "intrinsics"),
        ObservationTopic(
            CAMERA_IMAGE,
            "sensor_msgs/msg/CompressedImage",
            f"the pitch from above ({CAMERA!r}), JPEG, every {CAMERA_EVERY} ticks",
            period=CAMERA_EVERY,
            on_demand=True,
        ),
    ]
    attributes = {
        "__doc__": f"dm_control's soccer, {team_size} BoxHead walker(s) a side.",
        "__module__": __name__,
        "name": name,
        "version": VERSION,
        "params": PARAMS,
        "commands": tuple(commands),
        "observations": tuple(observations),
        "team_size": team_size,
    }
    made = type(f"Soccer{team_size}v{team_size}", (SoccerTask,), attributes)
    assert issubclass(made, SoccerTask)
    return made


PARAMS = Params(
    [
        Param(
            "time_limit",
            TIME_LIMIT,
            "seconds of simulation time a leg lasts if nobody scores",
            minimum=CONTROL_TIMESTEP,
            maximum=LONGEST,
        ),
        Param("camera_width", 320, "camera image width, pixels", 16, 640),
        Param("camera_height", 240, "camera image height, pixels", 16, 480),
    ]
)


def actions_of(team_size: int) -> Actions:
    """Home's players' three values each, as one vector: what a lone learner (Gymnasium,
    the live page's sliders) plays, as the exports' ``action``. The away side's messages
    are zeros: it stands still."""
    template = {"layout": {"dim": [], "data_offset": 0}, "data": [0.0] * len(ACTUATORS)}
    dimensions = []
    templates = {}
    for side in SIDES:
        for i in range(team_size):
            topic = player(side, i) + "action"
            templates[topic] = (ARRAY, template)
            if side == SIDES[0]:
                dimensions += [
                    Dimension(f"{side}.player_{i}.{name}", topic, f"data.{k}", -1.0, 1.0)
                    for k, name in enumerate(ACTUATORS)
                ]
    return Actions(dimensions=tuple(dimensions), templates=templates)
