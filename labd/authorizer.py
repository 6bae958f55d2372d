"""The lab's own authorizer: keys of its reservations, checked in process.

``labd serve --reservations`` puts each live robot behind it: a key opens the robot it
was booked for, from its slot's start to its end, and the bridge learns whose key it is
(the robot lets only that person drive, and files the drive under their name). Outside
bridges ask the same question over HTTP, at ``/api/auth`` (``labd.api.reservations``).
"""

from __future__ import annotations

import asyncio

from labd.bridge.auth import AuthError, Grant
from repository.errors import KeyRefused
from repository.reservations import Reservations


def ref(reservation_id: int) -> str:
    """What a reservation's key opens, as the bridge names it (``Grant.ref``)."""
    return f"reservation:{reservation_id}"


class ReservationAuthorizer:
    """An ``Authorizer`` that reads the reservations directly (no HTTP hop)."""

    def __init__(self, reservations: Reservations) -> None:
        self.reservations = reservations

    async def authorize(self, key: str, graph: str) -> Grant:
        try:
            access = await asyncio.to_thread(self.reservations.authorize, key, graph)
        except KeyRefused as err:
            raise AuthError(err.reason) from None
        booked = access.reservation
        return Grant(access.seconds, user=booked.user, ref=ref(booked.id))
