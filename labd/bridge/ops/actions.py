"""send_action_goal, cancel_action_goal, action_feedback, action_result,
advertise_action, unadvertise_action.

A client sends a goal to any action in the graph and hears back ``action_feedback``
frames (if it asked for ``feedback``) and exactly one ``action_result`` carrying its
goal id: ``result: true`` with the server's status (4 succeeded, 5 canceled, 6 aborted)
and values, or ``result: false`` with a sentence in ``values``. A goal that was never
accepted (no such action, invalid goal) ends with status 0 (unknown).

A client that advertises an action receives goals as ``send_action_goal`` frames with
a fresh id, cancellations as ``cancel_action_goal`` frames with that id, and answers
with ``action_feedback`` and ``action_result``.
"""

from __future__ import annotations

import itertools
from collections.abc import Iterable
from typing import Any

from labd.bridge.frames import (
    ActionFeedback,
    ActionResult,
    AdvertiseAction,
    CancelActionGoal,
    Id,
    SendActionGoal,
    UnadvertiseAction,
)
from labd.bridge.ops.services import failure_text
from labd.bridge.session import Capability, Handler, Session
from labd.errors import GraphError, LimitError, MessageError
from labd.graph.actions import UNKNOWN, Action, Goal, GoalResult
from labd.graph.message import Message


class Actions(Capability):
    def __init__(self, session: Session) -> None:
        super().__init__(session)
        self.sent: dict[str, Goal] = {}  # goals this client sent, by its id
        self.provided: dict[str, Action] = {}  # by absolute name
        self.serving: dict[str, Goal] = {}  # goals sent to this client's actions, by our id
        self._ids = itertools.count(1)

    def handlers(self) -> Iterable[Handler[Any]]:
        return (
            Handler(SendActionGoal, self.send_goal),
            Handler(CancelActionGoal, self.cancel),
            Handler(ActionFeedback, self.feedback),
            Handler(ActionResult, self.result),
            Handler(AdvertiseAction, self.advertise),
            Handler(UnadvertiseAction, self.unadvertise),
        )

    # -- sending goals -------------------------------------------------------------------

    def send_goal(self, op: SendActionGoal) -> None:
        session = self.session
        key = str(op.id) if op.id is not None else f"anonymous:{next(self._ids)}"

        def frame(kind: str, **fields: Any) -> dict[str, Any]:
            out: dict[str, Any] = {"op": kind}
            if op.id is not None:
                out["id"] = op.id
            out["action"] = op.action
            out.update(fields)
            return out

        def send(out: dict[str, Any]) -> None:
            session.send(out, op.compression or "none", op.fragment_size)

        def on_feedback(message: Message) -> None:
            send(frame("action_feedback", values=message.data))

        def on_result(result: GoalResult) -> None:
            if goal_box[0] is not None and self.sent.get(key) is goal_box[0]:
                del self.sent[key]
            if result.error:
                send(
                    frame("action_result", values=result.error, status=result.status, result=False)
                )
            else:
                values = result.result.data if result.result is not None else {}
                send(frame("action_result", values=values, status=result.status, result=True))

        if key in self.sent:
            raise GraphError(f"a goal with id {op.id!r} is already in progress")
        if len(self.sent) >= session.config.max_pending:
            refused = LimitError("goals in progress", session.config.max_pending)
            send(frame("action_result", values=str(refused), status=UNKNOWN, result=False))
            raise refused  # every goal ends with one action_result, a refused one too
        goal_box: list[Goal | None] = [None]
        try:
            goal = session.node.send_goal(
                session.resolve(op.action),
                op.args,
                on_result,
                on_feedback if op.feedback else None,
                type_name=op.action_type,
            )
        except MessageError as err:
            send(
                frame(
                    "action_result",
                    values=f"send_action_goal: {err.prefixed('args')}",
                    status=UNKNOWN,
                    result=False,
                )
            )
            raise err.prefixed("args") from None
        except GraphError as err:
            send(frame("action_result", values=str(err), status=UNKNOWN, result=False))
            raise
        if not goal.done:
            goal_box[0] = goal
            self.sent[key] = goal

    def cancel(self, op: CancelActionGoal) -> None:
        goal = self.sent.get(str(op.id))
        if goal is None:
            self.session.report(
                "warning", f"cancel_action_goal: no goal {op.id!r} in progress", op.id
            )
            return
        goal.cancel()

    # -- serving goals -------------------------------------------------------------------

    def advertise(self, op: AdvertiseAction) -> None:
        config = self.session.config
        name = self.session.resolve(op.action)
        if name not in self.provided and len(self.provided) >= config.max_services:
            raise LimitError("advertised actions", config.max_services)
        spelling = op.action

        def forward(goal: Goal) -> None:
            goal_id = f"action_goal:{spelling}:{next(self._ids)}"
            self.serving[goal_id] = goal

            def on_cancel() -> None:
                if goal.done:
                    self.serving.pop(goal_id, None)
                self.session.send({"op": "cancel_action_goal", "id": goal_id, "action": spelling})

            goal.on_cancel = on_cancel
            self.session.send(
                {
                    "op": "send_action_goal",
                    "id": goal_id,
                    "action": spelling,
                    "action_type": goal.action.type.name,
                    "args": goal.goal.data,
                    "feedback": True,
                }
            )

        self.provided[name] = self.session.node.provide_action(name, op.type, forward)
        self.session.report("info", f"advertised action {name}", op.id)

    def unadvertise(self, op: UnadvertiseAction) -> None:
        action = self.provided.pop(self.session.resolve(op.action), None)
        if action is None:
            self.session.report(
                "warning",
                f"unadvertise_action: {op.action} is not advertised by this client",
                op.id,
            )
            return
        self._forget(action)
        action.close()

    def _served(self, op_id: Id, op: str) -> Goal | None:
        goal = self.serving.get(str(op_id))
        if goal is None or goal.done:
            self.serving.pop(str(op_id), None)
            self.session.report("warning", f"{op}: no goal {op_id!r} is in progress here", op_id)
            return None
        return goal

    def feedback(self, op: ActionFeedback) -> None:
        goal = self._served(op.id, "action_feedback")
        if goal is not None:
            try:
                goal.feedback(op.values if op.values is not None else {})
            except MessageError as err:
                raise err.prefixed("values") from None

    def result(self, op: ActionResult) -> None:
        goal = self._served(op.id, "action_result")
        if goal is None:
            return
        del self.serving[str(op.id)]
        if not op.result:
            goal.fail(failure_text(op.values, f"{goal.action.name} failed"))
            return
        try:
            goal.finish(op.status, op.values if isinstance(op.values, dict) else None)
        except MessageError as err:
            raise err.prefixed("values") from None

    def _forget(self, action: Action) -> None:
        for goal_id, goal in list(self.serving.items()):
            if goal.action is action:
                del self.serving[goal_id]

    def close(self) -> None:
        self.sent.clear()
        self.serving.clear()
        for action in self.provided.values():
            action.close()
        self.provided.clear()
