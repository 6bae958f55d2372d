"""Failed attempts, counted: guessing passwords and keys is slowed down and logged.

Each kind of attempt (a password for a user, any password from an address, a key from
an address) may fail ``limit`` times in ``window`` seconds; past that the next attempt
is refused at once (``TooMany``, 429 with ``Retry-After``), without checking it, until
the oldest failure leaves the window. Only failures count, so a person who types their
password right is never slowed down by the limit, and each lock-out is logged once
with what was guessed at and from where.
"""

from __future__ import annotations

import logging
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

from labd.api.errors import TooMany

log = logging.getLogger("labd.api.throttle")


@dataclass(frozen=True)
class Limit:
    limit: int  # failures allowed in the window
    window: float  # seconds


LIMITS = {
    "password": Limit(5, 300.0),  # per user name
    "address": Limit(20, 300.0),  # sign-ins per client address
    "key": Limit(20, 60.0),  # /api/auth keys per client address
}


class Throttle:
    """Failures per (kind, who), in sliding windows, on the clock given."""

    def __init__(self, clock: Callable[[], float], limits: dict[str, Limit] | None = None) -> None:
        self.clock = clock
        self.limits = limits or LIMITS
        self._failures: dict[tuple[str, str], deque[float]] = {}

    def check(self, kind: str, who: str, what: str) -> None:
        """Refuse (``TooMany``) if ``who`` failed too often lately; ``what`` is the
        attempt as the message names it ("sign-ins for alice")."""
        wait = self._wait(kind, who)
        if wait > 0:
            raise TooMany(
                f"too many failed {what}; wait {wait:.0f} s and try again", retry_after=wait
            )

    def fail(self, kind: str, who: str) -> None:
        """Count a failure; log when ``who`` reaches the limit."""
        rule = self.limits[kind]
        if len(self._failures) > 10_000:  # many guessers: forget those whose time is up
            for kind_who in list(self._failures):
                self._wait(*kind_who)
        times = self._failures.setdefault((kind, who), deque())
        times.append(self.clock())
        if len(times) == rule.limit:
            log.warning(
                "%d failed %s attempts for %s within %.0f s: refusing more for a while",
                rule.limit,
                kind,
                who,
                rule.window,
            )

    def _wait(self, kind: str, who: str) -> float:
        rule = self.limits[kind]
        times = self._failures.get((kind, who))
        if not times:
            return 0.0
        now = self.clock()
        while times and times[0] <= now - rule.window:
            times.popleft()
        if not times:
            del self._failures[(kind, who)]
            return 0.0
        return times[0] + rule.window - now if len(times) >= rule.limit else 0.0
