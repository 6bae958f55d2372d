"""Booking live robots through the API, their public calendars, and the authorizer.

    GET  /api/reservations                     slots (filters robot, user, since, until):
                                               who and when, never keys
    POST /api/reservations                     book: {"robot", "start", "end" or "minutes"};
                                               the answer carries the slot's key
    GET  /api/reservations/{id}                one slot
    POST /api/reservations/{id}/extend         {"end"} or {"minutes"} more, if free after it
    POST /api/reservations/{id}/release        end it now (cancel it, before it began)
    GET  /api/reservations/{id}/key            its key, for the one who booked it
    GET  /api/robots/{robot}/key               my key of the robot's slot running now
    GET  /api/robots/{robot}/calendar.ics      the robot's calendar, to subscribe to
    GET  /api/auth?key=K[&robot=R][&callback=F]
                                               the rosjs paper's authorizer: {"seconds": N},
                                               N the time left in the key's slot, 0 for a
                                               key that opens nothing now; JSONP with F

The rules (slot length, limits per day and week, how far ahead, no overlap) are the
operator's, enforced by ``repository.reservations``; a refusal is a 4xx naming the rule.
When a slot is extended or released, the app's ``on_reservation`` is told
(``labd.api.state``), so that the lab's bridge moves or ends the connections made with
its key.
"""

from __future__ import annotations

import datetime as dt
import re
from dataclasses import dataclass
from typing import Annotated

import orjson
from fastapi import APIRouter, Depends, Query, Request
from fastapi.responses import JSONResponse, Response
from icalendar import Calendar, Event
from pydantic import BaseModel, ConfigDict, Field

from labd.api.common import Caller, Lab, Writer
from labd.api.errors import ApiError, responses
from labd.api.models import Booked, Id, KeyView, ReservationList, ReservationView
from labd.api.state import App, AppState
from repository.errors import KeyRefused, UnknownKey
from repository.reservations import Reservation, when
from repository.units import moment

router = APIRouter(tags=["reservations"])
CALLBACK = re.compile(r"[A-Za-z_$][\w$]*(\.[A-Za-z_$][\w$]*){0,4}")
NO_STORE = {"Cache-Control": "no-store"}
PAST = 30 * 86400.0  # how far back a calendar feed goes


class BookRequest(BaseModel):
    """A slot to book: its start (default now) and its end or its length in minutes."""

    model_config = ConfigDict(extra="forbid")
    robot: str = Field(description="a live robot of this lab, e.g. icreate-1")
    start: dt.datetime | None = Field(None, description="default: now; no zone: UTC")
    end: dt.datetime | None = Field(None, description="give this or minutes")
    minutes: float | None = Field(None, description="the slot's length; give this or end")


class ExtendRequest(BaseModel):
    """A later end for a slot: the new end, or minutes more."""

    model_config = ConfigDict(extra="forbid")
    end: dt.datetime | None = None
    minutes: float | None = Field(None, description="minutes added to the slot's end")


class AuthAnswer(BaseModel):
    """The rosjs paper's authorizer answer: how long the key may stay connected."""

    seconds: float = Field(description="seconds left in the key's slot; 0: it opens nothing now")
    reason: str | None = Field(None, description="why it opens nothing, when seconds is 0")


def view(r: Reservation, request: Request, now: float) -> ReservationView:
    return ReservationView(
        id=r.id,
        robot=r.robot,
        user=r.user,
        start=moment(r.start),
        end=moment(r.end),
        booked_end=moment(r.booked_end),
        created=moment(r.created),
        released=None if r.released is None else moment(r.released),
        state=r.state(now),
        minutes=round(r.seconds / 60, 2),
        calendar=f"{_base(request)}/reservations/{r.robot}",
    )


def key_view(r: Reservation, key: str, request: Request, now: float) -> KeyView:
    left = r.end - now if r.start <= now < r.end else 0.0
    return KeyView(
        key=key,
        robot=r.robot,
        path=f"/robots/{r.robot}",
        seconds=round(max(0.0, left), 3),
        reservation=view(r, request, now),
    )


def check_robot(app: AppState, robot: str) -> None:
    """Refuse (404) a robot that cannot be booked here, naming those that can."""
    if robot not in app.robots:
        listed = ", ".join(app.robots) or "none"
        message = f"no live robot {robot!r} here; the robots that can be booked: {listed}"
        raise ApiError(404, message, title=f"No robot {robot}")


@dataclass(frozen=True)
class SlotQuery:
    """The filters of GET /api/reservations."""

    robot: str | None = None
    user: str | None = None
    since: Annotated[dt.datetime | None, Query(description="default: now")] = None
    until: dt.datetime | None = None
    limit: Annotated[int, Query(ge=1, le=1000)] = 200


@router.get("/api/reservations", responses=responses(422))
def list_reservations(
    request: Request, service: Lab, q: Annotated[SlotQuery, Depends()]
) -> ReservationList:
    """Booked slots by start time (default: those not ended yet). Public: who and when."""
    now = service.index.clock()
    found = service.reservations.find(
        robot=q.robot,
        user=q.user,
        since=now if q.since is None else _epoch(q.since),
        until=None if q.until is None else _epoch(q.until),
        limit=q.limit,
    )
    return ReservationList(reservations=[view(r, request, now) for r in found])


@router.post(
    "/api/reservations",
    status_code=201,
    responses=responses(400, 401, 403, 404, 409, 422, 429),
)
def book(body: BookRequest, request: Request, service: Lab, app: App, user: Writer) -> JSONResponse:
    """Book a live robot for a slot; the answer has the slot's key."""
    check_robot(app, body.robot)
    now = service.index.clock()
    start = now if body.start is None else _epoch(body.start)
    if (body.end is None) == (body.minutes is None):
        raise ApiError(422, "give the slot's end or its length in minutes (one of them)")
    end = _epoch(body.end) if body.end is not None else start + float(body.minutes or 0) * 60
    made = service.reservations.book(user.name, body.robot, start, end)
    answer = Booked(
        reservation=view(made.reservation, request, now),
        key=key_view(made.reservation, made.key, request, now),
    )
    return JSONResponse(
        answer.model_dump(mode="json"),
        status_code=201,
        headers={"Location": f"/api/reservations/{made.reservation.id}", **NO_STORE},
    )


@router.get("/api/reservations/{reservation_id}", responses=responses(404))
def show(reservation_id: Id, request: Request, service: Lab) -> ReservationView:
    """One slot: who, which robot, when."""
    return view(service.reservations.get(reservation_id), request, service.index.clock())


@router.post(
    "/api/reservations/{reservation_id}/extend",
    responses=responses(400, 401, 403, 404, 409, 422, 429),
)
def extend(
    reservation_id: Id,
    body: ExtendRequest,
    request: Request,
    app: App,
    user: Writer,
) -> ReservationView:
    """Make my slot end later, if the time after it is free and the rules allow."""
    if (body.end is None) == (body.minutes is None):
        raise ApiError(422, "give the new end or the minutes to add (one of them)")
    service = app.service
    current = service.reservations.get(reservation_id)
    end = _epoch(body.end) if body.end is not None else current.end + float(body.minutes or 0) * 60
    longer = service.reservations.extend(user.name, reservation_id, end)
    app.on_reservation(longer)
    return view(longer, request, service.index.clock())


@router.post("/api/reservations/{reservation_id}/release", responses=responses(401, 403, 404, 422))
def release(
    reservation_id: Id, request: Request, service: Lab, app: App, user: Writer
) -> ReservationView:
    """End my slot now (or cancel it, before it began): the rest is free for others, and
    a client connected with its key is disconnected."""
    released = service.reservations.release(user.name, reservation_id)
    app.on_reservation(released)
    return view(released, request, service.index.clock())


@router.get("/api/reservations/{reservation_id}/key", responses=responses(401, 403, 404))
def key(reservation_id: Id, request: Request, service: Lab, user: Writer) -> JSONResponse:
    """The key of my slot, for a script or a page to connect with."""
    secret = service.reservations.key(user.name, reservation_id)
    found = service.reservations.get(reservation_id)
    body = key_view(found, secret, request, service.index.clock())
    return JSONResponse(body.model_dump(mode="json"), headers=NO_STORE)


@router.get(
    "/api/robots/{robot}/key",
    response_model=KeyView,
    responses=responses(401, 403, 404),
)
def current_key(robot: str, request: Request, service: Lab, app: App, user: Writer) -> JSONResponse:
    """The key of my slot of ``robot`` that runs now (the robot's page asks for it)."""
    check_robot(app, robot)
    now = service.index.clock()
    found = service.reservations.current(user.name, robot)
    if found is None:
        coming = service.reservations.find(robot=robot, user=user.name, since=now, limit=1)
        then = f"your next starts at {when(coming[0].start)}" if coming else "book one"
        raise ApiError(404, f"{user.name} has no slot of {robot} now; {then} (/reservations)")
    secret = service.reservations.key(user.name, found.id)
    body = key_view(found, secret, request, now)
    return JSONResponse(body.model_dump(mode="json"), headers=NO_STORE)


@router.get(
    "/api/robots/{robot}/calendar.ics",
    response_class=Response,
    responses={
        200: {"content": {"text/calendar": {}}, "description": "an iCalendar feed (RFC 5545)"},
        **responses(404),
    },
)
def calendar(robot: str, request: Request, service: Lab, app: App) -> Response:
    """The robot's slots as an iCalendar feed (who and when) for Google Calendar,
    Outlook or Thunderbird to subscribe to: from 30 days ago on."""
    check_robot(app, robot)
    now = service.index.clock()
    slots = service.reservations.find(robot=robot, since=now - PAST, released=True, limit=5000)
    return Response(
        ics(robot, slots, request),
        media_type="text/calendar; charset=utf-8",
        headers={"Content-Disposition": f'inline; filename="{robot}.ics"'},
    )


def ics(robot: str, slots: list[Reservation], request: Request) -> bytes:
    """An iCalendar document of ``robot``'s slots (one VEVENT each, UTC times)."""
    host = request.url.hostname or "labd"
    page = f"{_base(request)}/reservations/{robot}"
    cal = Calendar()
    cal.add("prodid", "-//labd//reservations//EN")
    cal.add("version", "2.0")
    cal.add("calscale", "GREGORIAN")
    cal.add("method", "PUBLISH")
    cal.add("x-wr-calname", f"{robot} (labd)")
    cal.add("x-wr-caldesc", f"Who has booked the live robot {robot}, and when")
    cal.add("x-wr-timezone", "UTC")
    cal.add("x-published-ttl", "PT15M")
    for slot in slots:
        event = Event()
        event.add("uid", f"reservation-{slot.id}@{host}")
        event.add("dtstamp", moment(slot.released or slot.created))
        event.add("created", moment(slot.created))
        event.add("dtstart", moment(slot.start))
        event.add("dtend", moment(slot.end))
        event.add("summary", f"{robot}: {slot.user}")
        note = f"{slot.user} has booked {robot}."
        if slot.released is not None:
            note += f" Released early, at {when(slot.released)}."
        event.add("description", note)
        event.add("url", page)
        event.add("status", "CONFIRMED")
        event.add("transp", "OPAQUE")
        cal.add_component(event)
    data: bytes = cal.to_ical()
    return data


@router.get(
    "/api/auth",
    tags=["authorizer"],
    response_model=AuthAnswer,
    responses={
        200: {
            "content": {"application/javascript": {}},
            "description": "the answer, as JSON, or as JSONP when a callback is given",
        },
        **responses(422, 429),
    },
)
async def auth(
    app: App,
    caller: Caller,
    key: Annotated[str, Query(max_length=256, description="the key to check")],
    callback: Annotated[str | None, Query(max_length=200, description="JSONP")] = None,
    robot: Annotated[str | None, Query(description="the robot it is presented to")] = None,
) -> Response:
    """The rosjs paper's authorizer: how many seconds ``key`` may stay connected (the
    time left in its slot; 0 for a key that opens nothing now, or that is not a key).
    An outside bridge asks this with ``labd serve --authorizer URL``; the lab's own
    bridge asks the same object in process. It runs on the event loop, with no thread
    of the API's own pool (``labd.authorizer`` says where the lookup runs)."""
    if callback is not None and not CALLBACK.fullmatch(callback):
        raise ApiError(422, "callback must be a JavaScript function name, such as authorize")
    caller.check("key", "failed keys from your address")
    try:
        access = await app.keys.check(key, robot)
        answer = AuthAnswer(seconds=round(access.seconds, 3), reason=None)
    except KeyRefused as err:
        if isinstance(err, UnknownKey):
            caller.fail("key")
        answer = AuthAnswer(seconds=0, reason=err.reason)
    headers = {**NO_STORE, "X-Content-Type-Options": "nosniff"}
    if callback is None:
        return JSONResponse(answer.model_dump(mode="json"), headers=headers)
    text = f"{callback}({orjson.dumps(answer.model_dump(mode='json')).decode()});"
    return Response(text, media_type="application/javascript", headers=headers)


def _base(request: Request) -> str:
    return str(request.base_url).rstrip("/")


def _epoch(moment: dt.datetime) -> float:
    if moment.tzinfo is None:
        moment = moment.replace(tzinfo=dt.UTC)
    return moment.timestamp()
