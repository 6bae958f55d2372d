"""Attempts, counted: guessing passwords and keys, and making accounts in bulk, are
slowed down and logged.

Each kind of attempt may happen ``limit`` times in ``window`` seconds; past that the
next one is refused at once (``TooMany``, 429 with ``Retry-After``), without checking
it, until the oldest leaves the window. Each lock-out is logged once with what was
guessed at and from where. What counts, and per what:

- ``password``: wrong passwords for one name *from one address*. Never per name alone:
  then anyone could lock anyone out by typing five wrong passwords for their name, and
  the owner, from their own address, signs in while the guesser is refused;
- ``address``: failed sign-ins (and refused sign-ups) from one address, any names;
- ``key``: keys the lab never made, from one address (``/api/auth``);
- ``signup``: accounts made from one address (every one counts, not only failures).

Only failures count for the first three, so a person who types their password right
is never slowed down by them. The address is the socket's peer, or what a proxy the
operator trusts says (``labd.api.common.client_address``); a route counts its caller's
attempts through the dependency ``labd.api.common.Caller`` (``Attempts``), the API's and
the pages' alike.
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
    "password": Limit(5, 300.0),  # wrong passwords per user name and client address
    "address": Limit(20, 300.0),  # failed sign-ins and sign-ups per client address
    "key": Limit(20, 60.0),  # /api/auth keys per client address
    "signup": Limit(5, 3600.0),  # accounts made per client address
}


def name_at(name: str, address: str) -> str:
    """Who the ``password`` limit counts: a name tried from an address."""
    return f"{name!r} from {address}"


@dataclass(frozen=True)
class Attempts:
    """One caller's attempts: the throttle's checks and counts for their address, or
    for a ``name`` tried from it (the ``password`` kind)."""

    throttle: Throttle
    address: str

    def check(self, kind: str, what: str, *, name: str | None = None) -> None:
        """Refuse (``TooMany``) if this caller tried ``kind`` too often lately; ``what``
        is the attempts as the message names them ("failed keys from your address")."""
        self.throttle.check(kind, self._who(name), what)

    def fail(self, kind: str, *, name: str | None = None) -> None:
        """Count an attempt of ``kind`` from this caller (a failure, or an account made)."""
        self.throttle.fail(kind, self._who(name))

    def _who(self, name: str | None) -> str:
        return self.address if name is None else name_at(name, self.address)


class Throttle:
    """Failures per (kind, who), in sliding windows, on the clock given."""

    def __init__(self, clock: Callable[[], float], limits: dict[str, Limit] | None = None) -> None:
        self.clock = clock
        self.limits = limits or LIMITS
        self._failures: dict[tuple[str, str], deque[float]] = {}

    def check(self, kind: str, who: str, what: str) -> None:
        """Refuse (``TooMany``) if ``who`` tried too often lately; ``what`` is the
        attempts as the message names them ("failed sign-ins for alice")."""
        wait = self._wait(kind, who)
        if wait > 0:
            raise TooMany(f"too many {what}; wait {wait:.0f} s and try again", retry_after=wait)

    def fail(self, kind: str, who: str) -> None:
        """Count an attempt of ``kind`` (a failure, or for ``signup`` an account made);
        log when ``who`` reaches the limit."""
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
