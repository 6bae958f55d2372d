"""The lab's own authorizer: keys of its reservations, checked in process.

``labd serve --reservations`` puts each live robot behind it: a key opens the robot it
was booked for, from its slot's start to its end, and the bridge learns whose key it is
(the robot lets only that person drive, and files the drive under their name). Outside
bridges ask the same question over HTTP, at ``/api/auth`` (``labd.api.reservations``),
which asks this same object.

A check reads one row of the index, so it runs on threads of its own, never on the
event loop (the robots step there) and never queued behind the work of the loop's
default executor (a worker's git checkout, a replay or a filing take seconds to
minutes there). Checks of one key that arrive while it is being looked up share that
one lookup: 200 clients presenting a slot's key at once cost one read, not 200.
"""

from __future__ import annotations

import asyncio
from concurrent.futures import ThreadPoolExecutor

from labd.bridge.auth import AuthError, Grant
from repository.errors import KeyRefused
from repository.reservations import Access, Reservations

THREADS = 4  # lookups of different keys at once


def ref(reservation_id: int) -> str:
    """What a reservation's key opens, as the bridge names it (``Grant.ref``)."""
    return f"reservation:{reservation_id}"


class ReservationAuthorizer:
    """An ``Authorizer`` that reads the reservations directly (no HTTP hop)."""

    def __init__(self, reservations: Reservations, *, threads: int = THREADS) -> None:
        self.reservations = reservations
        self._pool = ThreadPoolExecutor(threads, thread_name_prefix="labd-keys")
        self._asked: dict[tuple[int, str, str | None], asyncio.Future[Access]] = {}

    async def check(self, key: str, robot: str | None = None) -> Access:
        """What ``key`` opens now (on ``robot``, if given); ``KeyRefused`` saying why not."""
        loop = asyncio.get_running_loop()
        asked = (id(loop), key, robot)
        lookup = self._asked.get(asked)
        if lookup is None:
            lookup = loop.run_in_executor(self._pool, self.reservations.authorize, key, robot)
            self._asked[asked] = lookup
            lookup.add_done_callback(lambda done: self._answered(asked, done))
        # one caller giving up (its client left) must not cancel the others' lookup
        return await asyncio.shield(lookup)

    def _answered(self, asked: tuple[int, str, str | None], done: asyncio.Future[Access]) -> None:
        self._asked.pop(asked, None)
        if not done.cancelled():
            done.exception()  # retrieved here, so a lookup nobody awaits any more is quiet

    async def authorize(self, key: str, graph: str) -> Grant:
        try:
            access = await self.check(key, graph)
        except KeyRefused as err:
            raise AuthError(err.reason) from None
        booked = access.reservation
        return Grant(access.seconds, user=booked.user, ref=ref(booked.id))

    def close(self) -> None:
        self._pool.shutdown(wait=False, cancel_futures=True)
