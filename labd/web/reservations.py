"""The reservations' pages: every robot's calendar, booking, and my slots.

    GET  /reservations                    the robots and their next slots, the booking
                                          form, my slots (extend, release, their keys),
                                          and the rules
    POST /reservations                    book: robot, start (UTC, default now), minutes
    POST /reservations/{id}/extend        minutes more, if the time after is free
    POST /reservations/{id}/release       end it now, or cancel it before it began
    GET  /reservations/{robot}            the robot's calendar (public: who and when),
                                          with its iCalendar feed to subscribe to

Booking goes through the same rules as ``POST /api/reservations``; a refusal comes back
on the form with what was typed kept and the rule named. A slot changed here is told to
the lab's bridge, as through the API.
"""

from __future__ import annotations

import datetime as dt
from dataclasses import dataclass
from typing import Annotated, Any

from fastapi import APIRouter, Form, Request
from fastapi.responses import HTMLResponse, RedirectResponse
from pydantic import BaseModel

from labd.api.common import Lab
from labd.api.errors import ApiError
from labd.api.models import Id
from labd.api.reservations import changed, check_robot, robots
from labd.web.render import page
from labd.web.session import CsrfChecked, Viewer
from repository.errors import RecordNotFound, ReservationError
from repository.index import User
from repository.reservations import Reservation, duration
from repository.units import moment

router = APIRouter(include_in_schema=False)
DAY = 86400.0
AHEAD = 7 * DAY  # how far the overview looks ahead


@dataclass(frozen=True)
class Day:
    """A day of a robot's calendar and its slots."""

    date: dt.date
    slots: list[Reservation]


def _overview(
    request: Request,
    service: Lab,
    viewer: User | None,
    *,
    form: dict[str, str] | None = None,
    problem: str | None = None,
    done: str | None = None,
    status: int = 200,
) -> HTMLResponse:
    now = service.index.clock()
    names = robots(request)
    upcoming = {r: service.reservations.find(robot=r, since=now, until=now + AHEAD) for r in names}
    mine = service.reservations.find(user=viewer.name, since=now, limit=100) if viewer else []
    rules = service.reservations.rules
    return page(
        request,
        "reservations.html",
        {
            "robots": names,
            "upcoming": upcoming,
            "mine": mine,
            "now": now,
            "form": form or {"robot": names[0] if names else "", "start": "", "minutes": "30"},
            "problem": problem,
            "done": done,
            "rules": rules,
            "duration": duration,
            "reserved": _reserved(request),
        },
        user=viewer,
        status_code=status,
    )


def _reserved(request: Request) -> bool:
    """Whether the lab's robots are driven only with a reservation (labd serve --reservations)."""
    site = getattr(request.app.state, "site", None)
    return bool(getattr(site, "reservations", False))


@router.get("/reservations", response_class=HTMLResponse)
def overview(request: Request, service: Lab, viewer: Viewer, done: str = "") -> HTMLResponse:
    return _overview(request, service, viewer, done=done or None)


class BookForm(BaseModel):
    """The booking form's fields, as typed."""

    robot: str = ""
    start: str = ""
    minutes: str = "30"


@router.post("/reservations", response_class=HTMLResponse, dependencies=[CsrfChecked])
def book(request: Request, service: Lab, viewer: Viewer, sent: Annotated[BookForm, Form()]) -> Any:
    robot, start, minutes = sent.robot, sent.start, sent.minutes
    form = {"robot": robot, "start": start, "minutes": minutes}
    if viewer is None:
        return _overview(
            request, service, viewer, form=form, problem="sign in first to book", status=401
        )
    try:
        check_robot(request, robot)
        now = service.index.clock()
        begin = now if not start.strip() else _utc(start)
        length = float(minutes)
        made = service.reservations.book(viewer.name, robot, begin, begin + length * 60)
    except ValueError:
        problem = "give the start as YYYY-MM-DD HH:MM (UTC) and the length in minutes"
        return _overview(request, service, viewer, form=form, problem=problem, status=422)
    except (ApiError, ReservationError) as err:
        problem = err.message if isinstance(err, ApiError) else str(err)
        code = err.status if isinstance(err, ApiError) else 422
        return _overview(request, service, viewer, form=form, problem=problem, status=code)
    return RedirectResponse(
        f"/reservations?done=booked+reservation+{made.reservation.id}#mine", status_code=303
    )


@router.post("/reservations/{reservation_id}/extend", dependencies=[CsrfChecked])
def extend(
    request: Request,
    reservation_id: Id,
    service: Lab,
    viewer: Viewer,
    minutes: Annotated[str, Form()] = "15",
) -> Any:
    if viewer is None:
        return RedirectResponse("/session?then=/reservations", status_code=303)
    try:
        current = service.reservations.get(reservation_id)
        longer = service.reservations.extend(
            viewer.name, reservation_id, current.end + float(minutes) * 60
        )
    except ValueError:
        return _overview(request, service, viewer, problem="give minutes as a number", status=422)
    except (RecordNotFound, ReservationError) as err:
        return _overview(request, service, viewer, problem=str(err), status=422)
    changed(request, longer)
    return RedirectResponse(
        f"/reservations?done=extended+reservation+{reservation_id}#mine", status_code=303
    )


@router.post("/reservations/{reservation_id}/release", dependencies=[CsrfChecked])
def release(request: Request, reservation_id: Id, service: Lab, viewer: Viewer) -> Any:
    if viewer is None:
        return RedirectResponse("/session?then=/reservations", status_code=303)
    try:
        released = service.reservations.release(viewer.name, reservation_id)
    except (RecordNotFound, ReservationError) as err:
        return _overview(request, service, viewer, problem=str(err), status=422)
    changed(request, released)
    return RedirectResponse(
        f"/reservations?done=released+reservation+{reservation_id}#mine", status_code=303
    )


@router.get("/reservations/{robot}", response_class=HTMLResponse)
def calendar(request: Request, robot: str, service: Lab, viewer: Viewer) -> HTMLResponse:
    try:
        check_robot(request, robot)
    except ApiError as err:
        return page(
            request,
            "error.html",
            {"title": f"No robot {robot}", "message": err.message, "back": "/reservations"},
            user=viewer,
            status_code=404,
        )
    now = service.index.clock()
    first = now - now % DAY
    horizon = service.reservations.rules.horizon
    slots = service.reservations.find(
        robot=robot, since=first, until=now + horizon, released=True, limit=2000
    )
    days: list[Day] = []
    for slot in slots:
        date = moment(slot.start).date()
        if not days or days[-1].date != date:
            days.append(Day(date, []))
        days[-1].slots.append(slot)
    base = str(request.base_url).rstrip("/")
    feed = f"{base}/api/robots/{robot}/calendar.ics"
    return page(
        request,
        "calendar.html",
        {
            "robot": robot,
            "days": days,
            "now": now,
            "feed": feed,
            "webcal": "webcal" + feed[feed.index(":") :],
            "horizon": duration(horizon),
        },
        user=viewer,
    )


def _utc(text: str) -> float:
    """``YYYY-MM-DDTHH:MM`` (a datetime-local field) or with a space, as UTC."""
    moment = dt.datetime.fromisoformat(text.strip().replace(" ", "T"))
    if moment.tzinfo is None:
        moment = moment.replace(tzinfo=dt.UTC)
    return moment.timestamp()
