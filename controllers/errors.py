"""Exceptions of the controller-side client library.

Each carries its fields and formats itself with the lab's own sentence, so a
controller's log says what went wrong without a traceback hunt::

    LabError                  anything the lab or the connection refused
    ├── ConnectionLost        the WebSocket closed (code and reason)
    ├── LabTimeout            no answer within the time given (also a TimeoutError)
    ├── ServiceError          a service call failed: the lab's sentence
    ├── StatusError           the lab refused an op (publish, subscribe, ...): its error status
    └── EpisodeOver           /lab/step: the episode has ended (status, reason, the last tick)
"""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from controllers.client import Tick


class LabError(Exception):
    """Base class of the client library's errors."""


class ConnectionLost(LabError):
    """The connection to the lab closed, or could not be opened (``code`` is None)."""

    def __init__(
        self, url: str, code: int | None = None, reason: str = "", *, opened: bool = True
    ) -> None:
        self.url = url
        self.code = code
        self.reason = reason
        self.opened = opened
        detail = ": ".join(str(part) for part in (code, reason) if part)
        what = f"the connection to {url} closed" if opened else f"could not connect to {url}"
        super().__init__(what + (f" ({detail})" if detail else ""))


class LabTimeout(LabError, TimeoutError):
    """Nothing the client waited for arrived within ``seconds`` (wall clock)."""

    def __init__(self, what: str, seconds: float) -> None:
        self.what = what
        self.seconds = seconds
        super().__init__(f"{what}: nothing within {seconds:g} s")


class ServiceError(LabError):
    """A service call answered ``result: false``; ``message`` is the lab's sentence."""

    def __init__(self, service: str, message: str) -> None:
        self.service = service
        self.message = message
        super().__init__(f"{service} failed: {message}")


class StatusError(LabError):
    """The lab refused an operation and said why in an error status frame.

    Publishing is one-way, so the refusal of a publish (a NaN in a command, say)
    arrives later: it is raised by the next call that reads from the lab, once that
    call's own answer is in (so the subscriptions stay consistent).
    """

    def __init__(self, messages: list[str]) -> None:
        self.messages = messages
        super().__init__("the lab refused: " + "; ".join(messages))


class EpisodeOver(LabError):
    """The episode has ended: ``/lab/step`` answered that it did, or that it had.

    ``tick`` is the last tick of the episode; its observations are in the
    subscriptions. ``status`` is ``succeeded``, ``failed`` or ``truncated``,
    ``reason`` the lab's sentence, ``success`` whether the robot did its task.
    """

    def __init__(self, tick: Tick) -> None:
        self.tick = tick
        self.status = tick.status
        self.reason = tick.reason
        self.success = tick.success
        super().__init__(f"the episode is over: {tick.message}")
