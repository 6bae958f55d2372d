"""Actions in the graph: goals with feedback, a result, and cancellation.

The action server is an ``ActionHandler`` that receives each ``Goal``; it sends
feedback and finishes the goal with a status (``action_msgs/msg/GoalStatus``
numbering). The client's callbacks see the feedback and, exactly once, the result.
A client that cancels moves the goal to CANCELING and the server's ``on_cancel``
decides; a server without one is cancelled at once.

As in ROS 2, every action also has the service ``<action>/_action/cancel_goal``
(``action_msgs/srv/CancelGoal``), which anyone may call: ``Action.cancel_goals``
answers it with ROS 2's policy (a zero goal id and stamp cancel every goal of the
action, whoever sent it; a stamp cancels the goals accepted at or before it; an id,
that goal). Each goal has a UUID and the graph time it was accepted for this.
"""

from __future__ import annotations

import collections
import itertools
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from labd.errors import MessageError
from labd.graph.codec import codec_for
from labd.graph.message import Message
from labd.graph.services import args_to_value
from labd.graph.types import ActionType

if TYPE_CHECKING:
    from labd.graph.graph import Node
    from labd.graph.services import Service

# action_msgs/msg/GoalStatus
UNKNOWN, ACCEPTED, EXECUTING, CANCELING, SUCCEEDED, CANCELED, ABORTED = range(7)
TERMINAL = frozenset({SUCCEEDED, CANCELED, ABORTED})

CANCEL_GOAL = "action_msgs/srv/CancelGoal"
CANCEL_SERVICE = "/_action/cancel_goal"  # after the action's name
# action_msgs/srv/CancelGoal_Response return codes
ERROR_NONE, ERROR_REJECTED, ERROR_UNKNOWN_GOAL_ID, ERROR_GOAL_TERMINATED = range(4)
_ZERO_UUID = bytes(16)


@dataclass(frozen=True)
class GoalResult:
    """How a goal ended: its status, the result if any, and a reason on failure."""

    status: int
    result: Message | None = None
    error: str = ""

    @property
    def ok(self) -> bool:
        """True when the server finished the goal itself (any terminal status)."""
        return not self.error


GoalResultCallback = Callable[[GoalResult], None]
FeedbackCallback = Callable[[Message], None]
ActionHandler = Callable[["Goal"], None]

_goal_ids = itertools.count(1)
FINISHED_KEPT = 1000  # ended goals an action remembers, per action


class Action:
    """A named action and the node that serves it."""

    def __init__(self, node: Node, name: str, atype: ActionType, handler: ActionHandler) -> None:
        self.node = node
        self.name = name
        self.type = atype
        self.handler = handler
        self.goals: dict[str, Goal] = {}
        self.closed = False
        self.cancel_service: Service | None = None  # <action>/_action/cancel_goal
        # UUIDs of goals that ended, so a late cancel says "terminated", not "unknown".
        self._finished_uuids: collections.OrderedDict[bytes, None] = collections.OrderedDict()
        registry = node.graph.types
        self.goal_codec = codec_for(registry, atype.goal.name)
        self.result_codec = codec_for(registry, atype.result.name)
        self.feedback_codec = codec_for(registry, atype.feedback.name)

    def send_goal(
        self,
        client: Node,
        args: Mapping[str, Any] | list[Any] | None,
        on_result: GoalResultCallback,
        on_feedback: FeedbackCallback | None,
    ) -> Goal:
        value = args_to_value(self.type.goal, args)
        goal_msg = Message(self.goal_codec, self.goal_codec.normalize(value, self.node.graph.now))
        goal = Goal(self, client, goal_msg, on_result, on_feedback, accepted=self.node.graph.now())
        self.goals[goal.id] = goal
        client.goals.append(goal)
        self.handler(goal)
        return goal

    def cancel_goals(self, request: Mapping[str, Any]) -> dict[str, Any]:
        """Answer ``<action>/_action/cancel_goal``: cancel the goals ``goal_info`` names.

        ``request`` is an ``action_msgs/srv/CancelGoal`` request in normal form; the
        answer is its response. Goals that accept (all do here) are listed; the goal's
        server then decides how it ends, as with ``cancel_action_goal``.
        """
        info = request["goal_info"]
        uuid = bytes(info["goal_id"]["uuid"])
        stamp = (info["stamp"]["sec"], info["stamp"]["nanosec"])
        by_time = stamp != (0, 0)
        if uuid == _ZERO_UUID:
            chosen = [g for g in self.goals.values() if not by_time or g.accepted <= stamp]
        else:
            chosen = [
                g
                for g in self.goals.values()
                if g.uuid == uuid or (by_time and g.accepted <= stamp)
            ]
            if not any(g.uuid == uuid for g in chosen):
                known = uuid in self._finished_uuids
                code = ERROR_GOAL_TERMINATED if known else ERROR_UNKNOWN_GOAL_ID
                if not chosen:
                    return {"return_code": code, "goals_canceling": []}
        canceling = [g.info() for g in chosen]
        for goal in chosen:
            goal.cancel()
        return {
            "return_code": ERROR_NONE if canceling else ERROR_REJECTED,
            "goals_canceling": canceling,
        }

    def ended(self, goal: Goal) -> None:
        """Remember that ``goal`` ended (the last ``FINISHED_KEPT`` of them)."""
        self._finished_uuids[goal.uuid] = None
        if len(self._finished_uuids) > FINISHED_KEPT:
            self._finished_uuids.popitem(last=False)

    def close(self) -> None:
        """Withdraw the action; goals in progress are aborted."""
        if self.closed:
            return
        self.closed = True
        if self.cancel_service is not None:
            self.cancel_service.close()
        for goal in tuple(self.goals.values()):
            goal.fail(f"the server of {self.name} went away")
        graph = self.node.graph
        if graph.actions.get(self.name) is self:
            del graph.actions[self.name]
        self.node.actions.remove(self)


class Goal:
    """One goal, as both its server and its client see it."""

    def __init__(
        self,
        action: Action,
        client: Node,
        goal: Message,
        on_result: GoalResultCallback,
        on_feedback: FeedbackCallback | None,
        *,
        accepted: tuple[int, int] = (0, 0),
    ) -> None:
        number = next(_goal_ids)
        self.id = f"goal_{number}"
        self.uuid = number.to_bytes(16, "big")  # never zero, which means "every goal"
        self.accepted = accepted  # graph time (sec, nanosec)
        self.action = action
        self.client = client
        self.goal = goal
        self.status = ACCEPTED
        self._on_result: GoalResultCallback | None = on_result
        self._on_feedback = on_feedback
        self.on_cancel: Callable[[], None] | None = None  # set by the server

    @property
    def done(self) -> bool:
        return self._on_result is None

    def info(self) -> dict[str, Any]:
        """The goal as ``action_msgs/msg/GoalInfo`` (normal form)."""
        sec, nanosec = self.accepted
        return {"goal_id": {"uuid": self.uuid}, "stamp": {"sec": sec, "nanosec": nanosec}}

    # -- the server's side -------------------------------------------------------------

    def feedback(self, value: Mapping[str, Any] | Message) -> None:
        if self.done:
            return
        codec = self.action.feedback_codec
        msg = (
            value
            if isinstance(value, Message)
            else Message(codec, codec.normalize(value, self.action.node.graph.now))
        )
        if self.status == ACCEPTED:
            self.status = EXECUTING
        if self._on_feedback is not None:
            self._on_feedback(msg)

    def finish(self, status: int, value: Mapping[str, Any] | Message | None = None) -> None:
        """End the goal with a terminal status and a result (MessageError if it does not fit)."""
        if self.done:
            return
        if status not in TERMINAL:
            raise MessageError(
                f"must be SUCCEEDED (4), CANCELED (5) or ABORTED (6), got {status}", ["status"]
            )
        codec = self.action.result_codec
        try:
            if isinstance(value, Message):
                result = value
            else:
                result = Message(codec, codec.normalize(value or {}, self.action.node.graph.now))
        except MessageError as err:
            self.fail(
                f"the server of {self.action.name} sent an invalid result: {err.prefixed('values')}"
            )
            raise
        self.status = status
        self._finish(GoalResult(status, result))

    def fail(self, reason: str) -> None:
        """Abort without a result, saying why."""
        self.status = ABORTED
        self._finish(GoalResult(ABORTED, None, reason))

    # -- the client's side -------------------------------------------------------------

    def cancel(self) -> None:
        if self.done or self.status == CANCELING:
            return
        self.status = CANCELING
        if self.on_cancel is None:
            self.finish(CANCELED)
        else:
            self.on_cancel()

    def abandon(self) -> None:
        """The client went away: cancel, and drop whatever comes back."""
        if self.done:
            return
        self._on_feedback = None
        callback, self._on_result = self._on_result, None
        del callback
        self._forget()
        if self.on_cancel is not None:
            self.on_cancel()

    def _finish(self, result: GoalResult) -> None:
        callback = self._on_result
        if callback is None:
            return
        self._on_result = None
        self._forget()
        callback(result)

    def _forget(self) -> None:
        if self.action.goals.pop(self.id, None) is not None:
            self.action.ended(self)
        if self in self.client.goals:
            self.client.goals.remove(self)


ClientGoal = Goal
