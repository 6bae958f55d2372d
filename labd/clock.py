"""The time seam: what the protocol core needs from a clock.

An asyncio event loop satisfies ``Timers`` as it is (``loop.time()``,
``loop.call_later()``); unit tests pass a manual clock they advance themselves.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Protocol


class TimerHandle(Protocol):
    def cancel(self) -> None: ...


class Timers(Protocol):
    """A monotonic clock in seconds and one-shot timers on it."""

    def time(self) -> float: ...

    def call_later(self, delay: float, callback: Callable[..., Any], *args: Any) -> TimerHandle: ...
