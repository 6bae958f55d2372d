"""A simulated robot in a graph: a Simulation bound to topics and services.

The robot node subscribes to the task's command topics and publishes its
observation topics, with ``/clock`` (simulation time) and ``/lab/episode``. The
graph's clock is the simulation's, so every stamp, every ``rosapi/get_time`` and
every recorded log time is simulation time.

Two ways to run:

- **lockstep** (batch trials): the controller publishes its commands, then calls
  ``/lab/step`` (``std_srvs/srv/Trigger``). Commands reach the task as they are
  published, in order, so the step applies everything received before the call; it
  advances one control tick, publishes that tick's observations, and only then
  answers. Nothing depends on the wall clock, so the same inputs give the same data.
- **live** (teleoperation): ``LiveRunner`` steps on the wall clock while someone is
  connected. A ``geometry_msgs/Twist`` command that is not repeated within half a
  second is replaced by zero, as a real base's watchdog stops it. When an episode
  ends the robot shows it for a few seconds and starts the next one (next seed);
  ``/lab/reset`` starts a new one at once. With ``prompt`` (the live lab), a command
  that changes what the robot was told brings the next tick forward (see
  ``LiveRunner``): a key press moves the robot at once rather than at the next tick.

Commands are checked before anyone receives them (a gatekeeper subscription): a NaN
is refused with an error to the client that sent it, and never recorded.

Every topic the robot publishes is the lab's (``advertise(own=True)``): clients cannot
advertise or publish on an observation, ``/clock`` or ``/lab/episode``, so the record of
a trial or a demonstration holds the robot's observations and nobody else's.
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from collections.abc import Callable, Mapping
from typing import Any

from labd.errors import EpisodeOverError, GraphError
from labd.graph.graph import Graph, Node, Publisher, Side
from labd.graph.message import Message
from labd.graph.services import ServiceCall
from labd.sim import registry
from labd.sim.base import Stamp, stamp_of
from labd.sim.params import Value
from labd.sim.registry import TaskSpec
from labd.sim.simulation import Simulation
from repository.trial import EpisodeStatus
from repository.well_known import CLOCK, EPISODE

TWIST = "geometry_msgs/msg/Twist"
WATCHDOG = 0.5  # seconds a live Twist command holds
SHOW_END = 3.0  # seconds a live robot shows an ended episode before the next
EARLIEST = 0.25  # periods after a tick before a command may bring the next one forward
PAYBACK = 0.25  # periods a tick is lengthened by while the simulation runs ahead
ERROR_EVERY = 10.0  # seconds between two logged tracebacks of a live robot's failing ticks

log = logging.getLogger("labd.sim.robot")


class Robot:
    """One simulated robot, bound to ``graph``."""

    def __init__(
        self,
        graph: Graph,
        task: str | TaskSpec,
        params: Mapping[str, Any] | None = None,
        seed: int = 0,
        *,
        live: bool = False,
        node_name: str = "/robot",
        wall_clock: Callable[[], float] = time.monotonic,
        time_limit: float | None = None,
        blind: bool = False,
    ) -> None:
        self.graph = graph
        # A held-out episode's: /lab/episode says seed 0, so nothing the lab publishes
        # tells the controller which episode it runs (only what the task observes).
        self.blind = blind
        self.wall_clock = wall_clock  # live watchdogs only; trials never read it
        self.task = task
        self.live = live
        # Overrides the task's. Live robots have none unless their parameters give one
        # (``labd serve --param time_limit=S``): a person may drive as long as they like.
        self.time_limit = time_limit
        self.on_tick: Callable[[], None] | None = None  # called after every step
        # Live robots: who may command (labd.live decides); raises to refuse a command.
        self.command_gate: Callable[[Node | None, str], None] | None = None
        # The episode is about to be replaced (its simulation is still there to read).
        self.before_reset: Callable[[], None] | None = None
        self.on_reset: Callable[[], None] | None = None  # a new episode, before it is published
        # Live robots: a client's command changed what the robot was told (LiveRunner).
        self.on_command: Callable[[], None] | None = None
        spec = task if isinstance(task, TaskSpec) else registry.get(task)
        self.params = {**(spec.live_params if live else {}), **(params or {})}
        self.sim = self._simulation(seed)
        graph.clock = lambda: self.sim.time_ns
        graph.parameters = lambda: self.sim.values
        self.node = graph.create_node(node_name)
        self.publishers: dict[str, Publisher] = {}
        self.command_times: dict[str, float] = {}  # wall time of each live Twist command
        self._told: dict[str, dict[str, Any]] = {}  # live: the last command on each topic
        self._watchdog: dict[str, Publisher] = {}  # live: the stop a watchdog sends
        for command in self.sim.task.commands:
            self.node.subscribe(
                command.name,
                command.type,
                self._commander(command.name),
                gate=self._gate(command.name),
            )
            if live and command.type == TWIST:
                # the watchdog's stop is published, so a live session's record holds it
                self._watchdog[command.name] = self.node.advertise(command.name, TWIST)
        self._stale: set[str] = set()  # topics skipped because no one listened
        for obs in self.sim.task.observations:
            self._advertise(obs.name, obs.type, obs.latched)
        self._advertise(CLOCK, "rosgraph_msgs/msg/Clock", latched=False)
        self._advertise(EPISODE, "lab_msgs/msg/Episode", latched=True)
        if live:
            self.node.provide_service("/lab/reset", "std_srvs/srv/Trigger", self._reset_service)
        else:
            self.node.provide_service("/lab/step", "std_srvs/srv/Trigger", self._step_service)
        self.publish()

    @property
    def values(self) -> dict[str, Value]:
        return self.sim.values

    def _simulation(self, seed: int) -> Simulation:
        limit = self.time_limit
        if limit is None and self.live and "time_limit" not in self.params:
            limit = math.inf
        return Simulation(self.task, self.params, seed, time_limit=limit)

    # -- commands ----------------------------------------------------------------------

    def _commander(self, topic: str) -> Any:
        def take(message: Message) -> None:
            self.sim.task.command(topic, message.data)
            if not self.live:
                return
            if message.type_name == TWIST:
                self.command_times[topic] = self.wall_clock()
            if self._told.get(topic) != message.data:  # a held key's repeats are no change
                self._told[topic] = message.data
                if self.on_command is not None:
                    self.on_command()

        return take

    def _gate(self, topic: str) -> Any:
        take = self._commander(topic)

        def gate(message: Message, sender: Node | None) -> None:
            if sender is self.node:  # the watchdog's stop: no command to watch any more
                self.sim.task.command(topic, message.data)
                self._told[topic] = message.data
                return
            if self.command_gate is not None:
                self.command_gate(sender, topic)
            take(message)

        return gate

    def expire_commands(self, now: float) -> None:
        """Live mode: stop a Twist that has not been repeated for WATCHDOG seconds."""
        for topic, at in list(self.command_times.items()):
            if now - at > WATCHDOG:
                stop = self._watchdog.get(topic)
                del self.command_times[topic]
                if stop is not None:
                    stop.publish(self.graph.codec(TWIST).default())
                else:
                    self.sim.task.command(topic, self.graph.codec(TWIST).default())

    # -- ticks -------------------------------------------------------------------------

    def step(self) -> None:
        """Advance one control tick and publish what it produced (EpisodeOverError if over)."""
        self.sim.step()
        self.publish()
        if self.on_tick is not None:
            self.on_tick()

    def _advertise(self, topic: str, type_name: str, latched: bool) -> None:
        publisher = self.node.advertise(topic, type_name, latch=latched, own=True)
        publisher.topic.refresh = self._refresher(topic)
        self.publishers[topic] = publisher

    def publish(self) -> None:
        """Publish this tick's observations, /clock and /lab/episode.

        A topic that no one hears (no subscriber, no recorder) is not built; it is
        marked stale and built when someone subscribes, so subscribers still get the
        current state at once. A recorder hears every topic but the on-demand ones
        (cameras): those are built, and recorded, only while someone subscribes. A
        topic with period 0 is published when an episode begins, and then kept.
        """
        sim = self.sim
        stamp = stamp_of(sim.physics)
        due = [
            (o.name, o.on_demand)
            for o in sim.task.observations
            if (sim.tick == 0 if o.period == 0 else sim.tick % o.period == 0)
        ]
        recording = bool(self.graph.taps)
        for topic, on_demand in (*due, (CLOCK, False), (EPISODE, False)):
            # A topic not due this tick keeps its staleness: one published once, when the
            # episode began (/goal, /tf_static), still reaches a subscriber who comes later.
            self._stale.discard(topic)
            if self.publishers[topic].topic.subscriptions or (recording and not on_demand):
                self._publish_one(topic, stamp)
            else:
                self._stale.add(topic)

    def _publish_one(self, topic: str, stamp: Stamp) -> None:
        sim = self.sim
        if topic == CLOCK:
            data: dict[str, Any] | None = {"clock": stamp}
        elif topic == EPISODE:
            data = {
                "header": {"stamp": stamp, "frame_id": ""},
                "task": sim.spec.name,
                "seed": 0 if self.blind else sim.seed,
                "tick": sim.tick,
                "status": sim.status.value,
                "reason": sim.reason,
                "reward": sim.reward,
                "total_reward": sim.total_reward,
                "success": sim.status is EpisodeStatus.SUCCEEDED,
            }
        else:
            data = sim.task.observe(sim.physics, topic, stamp)
        if data is None:
            return
        if sim.spec.normal_form:  # built exactly as validation would leave it: trusted
            self.publishers[topic].publish_built(data)
        else:
            self.publishers[topic].publish(data)

    def _refresher(self, topic: str) -> Callable[[], None]:
        def refresh() -> None:
            if topic in self._stale:
                self._stale.discard(topic)
                self._publish_one(topic, stamp_of(self.sim.physics))

        return refresh

    def describe(self) -> str:
        sim = self.sim
        text = f"tick {sim.tick} at {sim.time_ns / 1e9:.3f} s: {sim.status}"
        return text + (f": {sim.reason}" if sim.reason else "")

    def _step_service(self, call: ServiceCall) -> None:
        try:
            self.step()
        except EpisodeOverError as err:
            call.reply({"success": False, "message": str(err)})
            return
        call.reply({"success": True, "message": self.describe()})

    # -- episodes ----------------------------------------------------------------------

    def reset(self, seed: int | None = None, *, publish: bool = True) -> None:
        """Start a new episode (the next seed unless one is given) and publish it (unless
        told not to: a recorder about to start publishes it itself)."""
        if self.before_reset is not None:
            self.before_reset()
        old = self.sim
        self.sim = self._simulation(self.sim.seed + 1 if seed is None else seed)
        old.close()
        self.command_times.clear()
        self._told.clear()
        if self.on_reset is not None:
            self.on_reset()
        if publish:
            self.publish()

    def _reset_service(self, call: ServiceCall) -> None:
        if self.command_gate is not None:
            try:
                self.command_gate(call.caller, "/lab/reset")
            except GraphError as err:
                call.reply({"success": False, "message": str(err)})
                return
        self.reset()
        call.reply({"success": True, "message": f"new episode, seed {self.sim.seed}"})

    def engaged(self) -> bool:
        """Someone is listening or commanding (live robots idle otherwise)."""
        if any(p.topic.subscriptions for p in self.publishers.values()):
            return True
        return any(
            p.side is Side.CLIENT for s in self.node.subscriptions for p in s.topic.publishers
        )

    def close(self) -> None:
        self.node.destroy()
        self.sim.close()


class LiveRunner:
    """Steps a live robot on the wall clock, at its control rate, while engaged.

    A command received between two ticks is applied by the next tick; on a fixed grid
    of ticks that is up to a period later (40 ms at 25 Hz), and it is the next ticks
    that show the robot moving. With ``prompt`` (the live lab), a command that changes
    what the robot was told (a key pressed or released; not a held key's repeats)
    runs the next tick at once, or a quarter period after the last tick if that is
    later, and the ticks after it follow one period apart from there. The simulation
    is then ahead of the wall clock by what the tick was brought forward (its
    ``lead``), never by more than one period: a command that would take it further
    waits. The lead is given back by making the ticks after the next a quarter of a
    period longer, so in the long run the robot keeps the wall clock's time and the camera
    its rate. The command is applied by that tick after the graph has delivered (and
    recorded) it, so a record replays as before.

    A tick that raises does not stop the runner: the robot is there for everyone, and
    one client's drive must not take it from them. The error is logged with its
    traceback (at most every ``ERROR_EVERY`` seconds, with how many there were) and the
    next tick comes as usual. What a drive does on a tick guards its own errors
    (``labd.live``); this is the last line, for bugs.
    """

    def __init__(self, robot: Robot, *, prompt: bool = False) -> None:
        self.robot = robot
        self.prompt = prompt
        self.ticks = 0
        self.early = 0  # ticks a command brought forward
        self.lead = 0.0  # seconds the ticks run ahead of the wall clock
        self._ended_at: float | None = None
        self.errors = 0  # ticks that raised
        self._logged_at: float | None = None
        self._commanded = False
        self._wake: asyncio.Future[None] | None = None

    async def run(self) -> None:
        loop = asyncio.get_running_loop()
        robot = self.robot
        if self.prompt:
            robot.on_command = self._command
        deadline = loop.time()
        try:
            while True:
                period = robot.sim.control_timestep
                if not robot.engaged():
                    await asyncio.sleep(0.1)
                    deadline = loop.time()
                    self.lead = 0.0
                    continue
                now = loop.time()
                early = now < deadline
                if early:  # a command brought this tick forward
                    self.lead += deadline - now
                    self.early += 1
                    deadline = now
                try:
                    self._tick(now)
                except Exception:  # a bug: logged, and the robot steps on for everyone
                    self.errors += 1
                    if self._log_error(now):
                        log.exception(
                            "%s: a tick failed (%d so far); the robot steps on",
                            robot.graph.name,
                            self.errors,
                        )
                # The frames that show the command's effect come a whole period apart.
                payback = 0.0 if early else min(self.lead, PAYBACK * period)
                self.lead -= payback
                deadline += period + payback
                if deadline < now - 5 * period:  # far behind (a slow render): do not rush
                    deadline = now
                    self.lead = 0.0
                earliest = max(now + EARLIEST * period, deadline - (period - self.lead))
                await self._pause(loop, deadline, earliest)
        finally:
            if robot.on_command == self._command:
                robot.on_command = None

    def _tick(self, now: float) -> None:
        robot = self.robot
        robot.expire_commands(robot.wall_clock())
        if robot.sim.status is EpisodeStatus.RUNNING:
            robot.step()
            self.ticks += 1
        elif self._ended_at is None:
            self._ended_at = now
        elif now - self._ended_at >= SHOW_END:
            self._ended_at = None
            robot.reset()

    def _log_error(self, now: float) -> bool:
        """Whether a tick's error is to be logged now: not on every tick of a run of them."""
        if self._logged_at is not None and now - self._logged_at < ERROR_EVERY:
            return False
        self._logged_at = now
        return True

    async def _pause(
        self, loop: asyncio.AbstractEventLoop, deadline: float, earliest: float
    ) -> None:
        """Until ``deadline``, or from ``earliest`` on once a command changed."""
        self._commanded = False
        while True:
            due = min(earliest, deadline) if self._commanded else deadline
            if loop.time() >= due:
                # Late (ticks slower than their period): still let the loop's other work
                # (clients, pages, the lab's own calls) run between two ticks.
                await asyncio.sleep(0)
                return
            wake = self._wake = loop.create_future()
            timer = loop.call_at(due, _resolve, wake)
            try:
                await wake
            finally:
                timer.cancel()
                self._wake = None

    def _command(self) -> None:
        self._commanded = True
        if self._wake is not None:
            _resolve(self._wake)


def _resolve(future: asyncio.Future[None]) -> None:
    if not future.done():
        future.set_result(None)
