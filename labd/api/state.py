"""The application's state: what every route of the lab's HTTP port shares, made once.

``create_app`` (``labd.api.app``) builds one ``AppState`` and keeps it on the app; a
route reaches it through the dependency ``App`` (``app: App``), and code outside a
route (a middleware, ``labd.lab``) through ``state_of(app)``. Nothing else is kept on
the app.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Annotated

from fastapi import Depends, Request
from starlette.applications import Starlette

from labd.api.builds import Builds
from labd.api.site import Scenes, Site
from labd.api.throttle import Throttle
from labd.authorizer import ReservationAuthorizer
from labd.service import Service
from repository.reservations import Reservation


@dataclass
class AppState:
    """What the routes share. ``site`` is replaced once the lab's bridge listens (its
    port, the drives, the robots' loop); the rest stays as made."""

    service: Service
    on_submit: Callable[[], None]  # a trial was queued: wake the workers
    robots: tuple[str, ...]  # the live robots that can be booked
    site: Site
    throttle: Throttle  # failed sign-ins, keys, sign-ups per address
    keys: ReservationAuthorizer  # /api/auth and the lab's bridge
    builds: Builds  # exports being built, and those kept
    on_reservation: Callable[[Reservation], None]  # tell the bridge of a changed slot
    scenes: Scenes = field(default_factory=Scenes)  # the live robots' 3D scenes


def state_of(app: Starlette) -> AppState:
    """The state ``create_app`` made for ``app``."""
    state = app.state.lab
    assert isinstance(state, AppState), "an app made by labd.api.app.create_app"
    return state


async def _app_state(request: Request) -> AppState:
    return state_of(request.app)


App = Annotated[AppState, Depends(_app_state)]
