"""``labd reserve``: book a live robot of a running lab, and manage the bookings.

    labd reserve book ROBOT [--start TIME] (--minutes N | --end TIME)
    labd reserve list [--robot R] [--user U]
    labd reserve extend ID (--minutes N | --end TIME)
    labd reserve release ID
    labd reserve key ID             print the slot's key (and nothing else)

TIME is ISO 8601 (``2030-01-07T10:00``, UTC unless it names a zone) or ``now``. Each
talks to the lab's HTTP API (``--server``); all but ``list`` write, and take ``--token``
(or ``LABD_TOKEN``). In the slot, a client connects to the robot on the lab's bridge
and sends the key first: ``{"op": "auth", "key": KEY}``.
"""

from __future__ import annotations

import argparse
import datetime as dt
from typing import Any

from labd.api.models import Booked, KeyView, ReservationList, ReservationView
from labd.commands.common import emit, fail, server_options
from repository.errors import ArchiveError
from scheduler.client import ApiClient
from scheduler.errors import RemoteError


def add_parser(commands: Any) -> None:
    reserve = commands.add_parser("reserve", help="book a live robot for a slot; your bookings")
    actions = reserve.add_subparsers(dest="action", required=True)

    p = actions.add_parser("book", help="book ROBOT for a slot and print its key")
    p.add_argument("robot", help="a live robot of the lab, e.g. icreate-1")
    p.add_argument("--start", default="now", help="ISO time, UTC unless zoned (default: now)")
    length = p.add_mutually_exclusive_group(required=True)
    length.add_argument("--minutes", type=float, help="the slot's length")
    length.add_argument("--end", help="the slot's end, ISO time")
    server_options(p, write=True)

    p = actions.add_parser("list", help="booked slots from now on: who and when")
    p.add_argument("--robot", help="only this robot's (default: every robot's)")
    p.add_argument("--user", help="only this person's (default: everyone's)")
    server_options(p)

    p = actions.add_parser("extend", help="make your slot end later, if the time after is free")
    p.add_argument("id", type=int, metavar="ID", help="the reservation's number")
    later = p.add_mutually_exclusive_group(required=True)
    later.add_argument("--minutes", type=float, help="minutes more")
    later.add_argument("--end", help="the new end, ISO time")
    server_options(p, write=True)

    p = actions.add_parser("release", help="end your slot now (cancel it, before it starts)")
    p.add_argument("id", type=int, metavar="ID", help="the reservation's number")
    server_options(p, write=True)

    p = actions.add_parser("key", help="print your slot's key, for a script to connect with")
    p.add_argument("id", type=int, metavar="ID", help="the reservation's number")
    server_options(p, write=True)


def main(args: argparse.Namespace) -> int:
    try:
        with ApiClient(args.server, getattr(args, "token", None)) as api:
            return ACTIONS[args.action](args, api)
    except (RemoteError, ArchiveError) as err:
        return fail(args, str(err))


def _book(args: argparse.Namespace, api: ApiClient) -> int:
    body: dict[str, Any] = {"robot": args.robot}
    if args.start != "now":
        body["start"] = _time(args.start)
    if args.minutes is not None:
        body["minutes"] = args.minutes
    else:
        body["end"] = _time(args.end)
    made = api.post("/api/reservations", Booked, json=body)
    slot = made.reservation
    emit(
        args,
        made.model_dump(mode="json"),
        lambda: [
            f"reservation {slot.id}: {slot.robot} from {_show(slot.start)} to {_show(slot.end)}",
            f"key: {made.key.key}",
            f"connect to {made.key.path} on the lab's bridge in the slot, and send the key"
            ' first: {"op": "auth", "key": KEY}',
        ],
    )
    return 0


def _list(args: argparse.Namespace, api: ApiClient) -> int:
    params = {k: v for k, v in (("robot", args.robot), ("user", args.user)) if v}
    found = api.get("/api/reservations", ReservationList, params=params).reservations
    emit(
        args,
        [r.model_dump(mode="json") for r in found],
        lambda: [_line(r) for r in found] or ["no slots booked from now on"],
    )
    return 0


def _extend(args: argparse.Namespace, api: ApiClient) -> int:
    body = {"minutes": args.minutes} if args.minutes is not None else {"end": _time(args.end)}
    slot = api.post(f"/api/reservations/{args.id}/extend", ReservationView, json=body)
    emit(args, slot.model_dump(mode="json"), lambda: [_line(slot)])
    return 0


def _release(args: argparse.Namespace, api: ApiClient) -> int:
    slot = api.post(f"/api/reservations/{args.id}/release", ReservationView)
    emit(args, slot.model_dump(mode="json"), lambda: [_line(slot)])
    return 0


def _key(args: argparse.Namespace, api: ApiClient) -> int:
    found = api.get(f"/api/reservations/{args.id}/key", KeyView)
    emit(args, found.model_dump(mode="json"), lambda: [found.key])
    return 0


ACTIONS = {
    "book": _book,
    "list": _list,
    "extend": _extend,
    "release": _release,
    "key": _key,
}


def _time(text: str) -> str:
    """An ISO time as the API takes it (UTC unless it names a zone); ArchiveError if not."""
    try:
        moment = dt.datetime.fromisoformat(text.strip())
    except ValueError:
        raise ArchiveError(f"{text!r} is not a time: write 2030-01-07T10:00 (UTC)") from None
    if moment.tzinfo is None:
        moment = moment.replace(tzinfo=dt.UTC)
    return moment.isoformat()


def _show(moment: dt.datetime) -> str:
    return moment.astimezone(dt.UTC).strftime("%Y-%m-%d %H:%M:%S UTC")


def _line(r: ReservationView) -> str:
    return (
        f"#{r.id:<5} {r.robot:<12} {_show(r.start)} to {_show(r.end)}"
        f" ({r.minutes:g} min) {r.user} [{r.state}]"
    )
