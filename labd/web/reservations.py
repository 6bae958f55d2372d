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

from fastapi import APIRouter, Depends, Form, Request
from fastapi.responses import HTMLResponse, RedirectResponse
from pydantic import BaseModel

from labd.api.errors import Invalid
from labd.api.models import Id
from labd.api.reservations import check_robot
from labd.api.state import App
from labd.web.problems import PageRoute, on_form
from labd.web.render import page
from labd.web.session import CsrfChecked, SignedIn, Viewer
from repository.index import User
from repository.reservations import Reservation, duration
from repository.units import moment

router = APIRouter(include_in_schema=False, route_class=PageRoute)
DAY = 86400.0
AHEAD = 7 * DAY  # how far the overview looks ahead
WHEN = "give the start as YYYY-MM-DD HH:MM (UTC) and the length in minutes"
# The booking forms come back to the overview, where they are.
Booker = Annotated[User, Depends(SignedIn("/reservations"))]


@dataclass(frozen=True)
class Day:
    """A day of a robot's calendar and its slots."""

    date: dt.date
    slots: list[Reservation]


def _overview(
    request: Request,
    app: App,
    viewer: User | None,
    *,
    form: dict[str, str] | None = None,
    problem: str | None = None,
    done: str | None = None,
    status: int = 200,
) -> HTMLResponse:
    service = app.service
    now = service.index.clock()
    names = app.robots
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
            "reserved": app.site.reservations,
        },
        user=viewer,
        status_code=status,
    )


@router.get("/reservations", response_class=HTMLResponse)
def overview(request: Request, app: App, viewer: Viewer, done: str = "") -> HTMLResponse:
    return _overview(request, app, viewer, done=done or None)


class BookForm(BaseModel):
    """The booking form's fields, as typed."""

    robot: str = ""
    start: str = ""
    minutes: str = "30"


@router.post("/reservations", response_class=HTMLResponse, dependencies=[CsrfChecked])
def book(request: Request, app: App, person: Booker, sent: Annotated[BookForm, Form()]) -> Any:
    robot, start, minutes = sent.robot, sent.start, sent.minutes
    form = {"robot": robot, "start": start, "minutes": minutes}
    with on_form(
        request,
        lambda problem, status: _overview(
            request, app, person, form=form, problem=problem, status=status
        ),
    ):
        check_robot(app, robot)
        now = app.service.index.clock()
        begin = now if not start.strip() else _utc(start)
        length = _number(minutes, WHEN)
        made = app.service.reservations.book(person.name, robot, begin, begin + length * 60)
    return RedirectResponse(
        f"/reservations?done=booked+reservation+{made.reservation.id}#mine", status_code=303
    )


@router.post("/reservations/{reservation_id}/extend", dependencies=[CsrfChecked])
def extend(
    request: Request,
    reservation_id: Id,
    app: App,
    person: Booker,
    minutes: Annotated[str, Form()] = "15",
) -> Any:
    service = app.service
    with on_form(
        request,
        lambda problem, status: _overview(request, app, person, problem=problem, status=status),
    ):
        more = _number(minutes, "give minutes as a number")
        current = service.reservations.get(reservation_id)
        longer = service.reservations.extend(person.name, reservation_id, current.end + more * 60)
    app.on_reservation(longer)
    return RedirectResponse(
        f"/reservations?done=extended+reservation+{reservation_id}#mine", status_code=303
    )


@router.post("/reservations/{reservation_id}/release", dependencies=[CsrfChecked])
def release(request: Request, reservation_id: Id, app: App, person: Booker) -> Any:
    with on_form(
        request,
        lambda problem, status: _overview(request, app, person, problem=problem, status=status),
    ):
        released = app.service.reservations.release(person.name, reservation_id)
    app.on_reservation(released)
    return RedirectResponse(
        f"/reservations?done=released+reservation+{reservation_id}#mine", status_code=303
    )


@router.get("/reservations/{robot}", response_class=HTMLResponse)
def calendar(request: Request, robot: str, app: App, viewer: Viewer) -> HTMLResponse:
    check_robot(app, robot)
    service = app.service
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


def _number(text: str, problem: str) -> float:
    """A number typed in a form (``Invalid`` saying ``problem`` if it is not one)."""
    try:
        return float(text)
    except ValueError:
        raise Invalid(problem) from None


def _utc(text: str) -> float:
    """``YYYY-MM-DDTHH:MM`` (a datetime-local field) or with a space, as UTC (``Invalid``
    if it is neither)."""
    try:
        moment = dt.datetime.fromisoformat(text.strip().replace(" ", "T"))
    except ValueError:
        raise Invalid(WHEN) from None
    if moment.tzinfo is None:
        moment = moment.replace(tzinfo=dt.UTC)
    return moment.timestamp()
