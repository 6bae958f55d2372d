"""Actions in the graph: goals with feedback, a result, and cancellation.

The action server is an ``ActionHandler`` that receives each ``Goal``; it sends
feedback and finishes the goal with a status (``action_msgs/msg/GoalStatus``
numbering). The client's callbacks see the feedback and, exactly once, the result.
A client that cancels moves the goal to CANCELING and the server's ``on_cancel``
decides; a server without one is cancelled at once.
"""

from __future__ import annotations

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

# action_msgs/msg/GoalStatus
UNKNOWN, ACCEPTED, EXECUTING, CANCELING, SUCCEEDED, CANCELED, ABORTED = range(7)
TERMINAL = frozenset({SUCCEEDED, CANCELED, ABORTED})


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


class Action:
    """A named action and the node that serves it."""

    def __init__(self, node: Node, name: str, atype: ActionType, handler: ActionHandler) -> None:
        self.node = node
        self.name = name
        self.type = atype
        self.handler = handler
        self.goals: dict[str, Goal] = {}
        self.closed = False
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
        goal = Goal(self, client, goal_msg, on_result, on_feedback)
        self.goals[goal.id] = goal
        client.goals.append(goal)
        self.handler(goal)
        return goal

    def close(self) -> None:
        """Withdraw the action; goals in progress are aborted."""
        if self.closed:
            return
        self.closed = True
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
    ) -> None:
        self.id = f"goal_{next(_goal_ids)}"
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
        self.action.goals.pop(self.id, None)
        if self in self.client.goals:
            self.client.goals.remove(self)


ClientGoal = Goal
