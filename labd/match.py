"""A leg of a match on the lab's side: two teams' controllers, one station, one tick.

Each side's controller reaches the station through a bridge of its own (its socket,
its connection limit) under its side's namespace (``/home``: it spells its players
``/player_0/...`` and its score ``/score``, and cannot reach the other side's). The
task advances only when every side has called ``/lab/step``. The ``StepBarrier``
answers no step call until every side has made one; then it delivers the commands each
side sent since its previous call, the first side's before the next's, steps once, and
answers every side together. So the record holds each tick in the same order however
the two sockets interleaved, and a rerun reproduces it byte for byte; and a command a
side sends while it waits for the other counts for the next tick, whatever the other's
timing. A side that never steps holds the leg at its tick: judging it late is the
runner's (``owing``), as judging a stall is; the barrier only waits.
"""

from __future__ import annotations

import collections
import dataclasses
from collections.abc import Callable, Collection, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from labd.bridge.frames import Id
from labd.bridge.server import BridgeServer
from labd.bridge.session import Hold, Session
from labd.errors import EpisodeOverError, LabError
from labd.graph.graph import Node, Publisher
from labd.graph.message import Message
from labd.graph.names import Namespace
from labd.graph.services import ServiceCall
from labd.recorded import StationLab
from labd.sim.robot import Robot
from repository.manifest import Manifest, Versions
from scheduler.host import MatchSetup

if TYPE_CHECKING:
    from labd.trial import LabHost

STEP = "/lab/step"
MAX_HELD = 256  # commands a side may send between two of its steps
MAX_CALLS = 4  # step calls a side may have waiting for the other side


@dataclass(frozen=True)
class _Held:
    """A command a side sent, kept until every side has stepped."""

    publisher: Publisher
    message: Message
    session: Session
    op_id: Id


class StepBarrier:
    """The shared tick of a match: ``/lab/step`` on ``robot`` answered once every side
    has called it. ``side_of`` tells which side a calling node is on (None: no side's);
    ``commands`` are the graph's command topics, which a side's ``hold`` keeps back
    until the tick they belong to."""

    def __init__(
        self,
        robot: Robot,
        sides: Sequence[str],
        commands: Collection[str],
        side_of: Callable[[Node], str | None],
    ) -> None:
        self.robot = robot
        self.sides = tuple(sides)
        self._commands = frozenset(commands)
        self._side_of = side_of
        self._held: dict[str, list[_Held]] = {side: [] for side in self.sides}
        self._calls: dict[str, collections.deque[tuple[ServiceCall, list[_Held]]]] = {
            side: collections.deque() for side in self.sides
        }
        # the robot's own /lab/step is replaced: the same node provides it again
        robot.node.provide_service(STEP, "std_srvs/srv/Trigger", self._call)

    def hold(self, side: str) -> Hold:
        """What keeps ``side``'s commands back until its next step call."""

        def hold(session: Session, publisher: Publisher, message: Message, op_id: Id) -> bool:
            if publisher.topic.name not in self._commands:
                return False  # a side's other topics go straight through
            held = self._held[side]
            if len(held) >= MAX_HELD:
                session.report(
                    "error",
                    f"publish: at most {MAX_HELD} commands between two steps; this one was dropped",
                    op_id,
                )
                return True
            held.append(_Held(publisher, message, session, op_id))
            return True

        return hold

    def owing(self) -> list[str]:
        """The sides the next tick waits for."""
        return [side for side in self.sides if not self._calls[side]]

    def _call(self, call: ServiceCall) -> None:
        side = self._side_of(call.caller)
        if side is None:
            call.fail(f"{STEP} is stepped by the match's teams only")
            return
        sim = self.robot.sim
        if not sim.running:
            call.reply({"success": False, "message": str(EpisodeOverError(sim.status, sim.reason))})
            return
        if len(self._calls[side]) >= MAX_CALLS:
            call.fail(f"{MAX_CALLS} step calls are already waiting for the other side")
            return
        self._calls[side].append((call, self._held[side]))
        self._held[side] = []
        self._release()

    def _release(self) -> None:
        """Step as long as every side has a call waiting."""
        while all(self._calls.values()):
            taken = [self._calls[side].popleft() for side in self.sides]
            for _, held in taken:  # the first side's commands, then the next's
                for command in held:
                    try:
                        command.publisher.publish(command.message)
                    except LabError as err:  # refused by the robot (a NaN), or revoked
                        command.session.report("error", f"publish: {err}", command.op_id)
            try:
                self.robot.step()
                answer = {"success": True, "message": self.robot.describe()}
            except EpisodeOverError as err:
                answer = {"success": False, "message": str(err)}
            for call, _ in taken:
                call.reply(answer)


class LabMatch(StationLab):
    """One leg of a match: its station, the step barrier, a bridge per side and the
    recorder of both (``scheduler.host.MatchLab``)."""

    def __init__(self, host: LabHost, setup: MatchSetup, *, out: Path) -> None:
        super().__init__(host.types, host.config, setup.task, setup.values, setup.seed, out=out)
        sim = self.robot.sim
        sides = tuple(sim.spec.sides)
        if tuple(setup.teams) != sides:
            self.station.close()
            named = ", ".join(setup.teams) or "none"
            raise LabError(
                f"{setup.task} is played by the sides {', '.join(sides) or 'none'} (in that"
                f" order); the leg names {named}"
            )
        self.manifest = Manifest.match(
            teams=setup.teams,
            task=self._task_version(),
            parameters=setup.values,
            seed=setup.seed,
            runtime=setup.runtime,
            versions=Versions.here(),
            model_sha256=sim.model_digest(),
        )
        # a side waits for the other as long as the runner lets it: no bridge timeout
        config = dataclasses.replace(host.config, service_timeout=0)
        self.barrier = StepBarrier(
            self.robot, sides, [c.name for c in sim.task.commands], self._side_of
        )
        self.by_side = {
            side: BridgeServer(
                {"trial": self.station.graph},
                config,
                namespaces={"trial": Namespace("/" + side)},
                hold=self.barrier.hold(side),
            )
            for side in sides
        }
        self.bridges = tuple(self.by_side.values())

    def _side_of(self, node: Node) -> str | None:
        for side, bridge in self.by_side.items():
            if any(c.session is not None and c.session.node is node for c in bridge.connections):
                return side
        return None

    def owing(self) -> list[str]:
        return self.barrier.owing()

    async def start(self, sockets: Mapping[str, Path]) -> None:
        await self._start([sockets[side] for side in self.by_side])
