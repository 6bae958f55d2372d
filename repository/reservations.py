"""Booking live robots: the operator's rules, enforced, and a key for each slot.

A person books a robot for a slot (``book``); the slot's **key** lets a client drive that
robot from the slot's start to its end, and no other robot, at no other time
(``authorize``). The rules are the operator's (``Rules``) and every booking, extension
and release goes through them:

- a slot lasts more than nothing and at most ``max_slot`` (a day at most); it starts
  now or later (a slot booked for a moment ago starts when the request arrives), and at
  most ``horizon`` ahead (a year at most): so every time a booking can hold is a date
  people can read, and a time out of the calendar is refused before it is looked at;
- no two slots of a robot overlap;
- a person has at most so many slots, and so many minutes of slots, per day and per
  week (UTC calendar days, ISO weeks from Monday; a slot counts on the day it starts);
- an extension is a longer slot: it is allowed only if the time after the slot is free
  and the longer slot keeps to the rules;
- an early release ends the slot now (or cancels it, before it began): the rest of
  the slot is free for others, and no longer counts against the person's limits.

Each of these reads and then writes in one transaction that no other booking can
interleave with: on SQLite, write transactions run one at a time (``BEGIN IMMEDIATE``);
on PostgreSQL, an advisory lock held until the transaction ends. So of two clients
racing for overlapping slots, exactly one wins, on either database.

Keys are never stored: a key is the reservation's id and an HMAC of it (with a random
nonce kept in the row) under the lab's secret (``load_secret``, a file beside the
signing keys, not in the database), so a copy of the database opens no robot, and the
owner can fetch their key again at any time. A key is parsed strictly (ASCII, its exact
shape) before anything is looked up. Revoking a person (``rekey``) gives their slots new
nonces: every key they held opens nothing from then on, and the slots stay booked.
"""

from __future__ import annotations

import base64
import hashlib
import hmac
import logging
import math
import os
import re
import secrets
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import sqlalchemy as sa
from sqlalchemy.engine import Connection

from repository.errors import (
    KeyRefused,
    MalformedKey,
    NotYourReservation,
    OverLimit,
    RecordNotFound,
    ReservationError,
    SlotTaken,
    UnknownKey,
)
from repository.index import Index
from repository.slots import State
from repository.tables import reservations
from repository.units import moment

log = logging.getLogger("repository.reservations")
R = reservations.c
DAY = 86400.0
KEY_PREFIX = "labd_rk_"
SECRET_BYTES = 32
# A key: the prefix, the reservation's number, and its HMAC-SHA256 in URL-safe base64
# without padding (43 characters); ASCII only, so no other digits or letters pass.
KEY = re.compile(r"labd_rk_([1-9][0-9]{0,11})_([A-Za-z0-9_-]{43})", re.ASCII)
MAX_SLOT = DAY  # the longest ``max_slot`` an operator may set
MAX_HORIZON = 365 * DAY  # the furthest ``horizon`` an operator may set


@dataclass(frozen=True)
class Rules:
    """The operator's rules for booking live robots (``None``: no such limit)."""

    max_slot: float = 3600.0  # seconds a slot may last
    max_slots_per_day: int | None = 4
    max_minutes_per_day: float | None = 120.0
    max_slots_per_week: int | None = 12
    max_minutes_per_week: float | None = 480.0
    horizon: float = 14 * DAY  # how far ahead a slot may start, in seconds
    grace: float = 60.0  # a slot may be asked for this long ago (it then starts now)

    def __post_init__(self) -> None:
        if not 0 < self.max_slot <= MAX_SLOT:
            raise ValueError(f"a slot may last more than 0 and at most {duration(MAX_SLOT)}")
        if not 0 < self.horizon <= MAX_HORIZON:
            raise ValueError(
                f"slots may be booked more than 0 and at most {duration(MAX_HORIZON)} ahead"
            )


@dataclass(frozen=True)
class Reservation:
    """A booked slot: who, which robot, when (``end`` as it stands after any release)."""

    id: int
    robot: str
    user: str
    start: float
    end: float
    booked_end: float
    created: float
    released: float | None

    def state(self, now: float) -> State:
        if self.released is not None:
            return "released"
        if now < self.start:
            return "upcoming"
        return "current" if now < self.end else "ended"

    @property
    def seconds(self) -> float:
        return max(0.0, self.end - self.start)


@dataclass(frozen=True)
class Booking:
    """A new reservation and its key."""

    reservation: Reservation
    key: str


@dataclass(frozen=True)
class Access:
    """What a valid key opens: its reservation, and the seconds left in its slot."""

    reservation: Reservation
    seconds: float


class Reservations:
    """The reservations on ``index``, under ``rules``, with keys made with ``secret``."""

    def __init__(self, index: Index, rules: Rules, secret: bytes) -> None:
        if len(secret) < 16:
            raise ValueError("the reservations' secret must have at least 16 bytes")
        self.index = index
        self.rules = rules
        self._secret = secret

    # -- booking ------------------------------------------------------------------------

    def book(self, user: str, robot: str, start: float, end: float) -> Booking:
        """Book ``robot`` for ``user`` from ``start`` to ``end`` (epoch seconds)."""
        now = self.index.clock()
        self._check_times(now, start, end)
        if end <= start:
            raise ReservationError(
                f"a slot must end after it starts: {when(start)} to {when(end)} lasts"
                f" {duration(end - start)}; give a later end"
            )
        if start < now - self.rules.grace or end <= now:
            raise ReservationError(
                f"the slot starts at {when(start)}, in the past (it is {when(now)} now);"
                " book a time from now on"
            )
        start = max(start, now)
        if start > now + self.rules.horizon:
            raise ReservationError(
                f"a slot may start at most {duration(self.rules.horizon)} ahead, by"
                f" {when(now + self.rules.horizon)}; this one starts at {when(start)}"
            )
        self._check_length(end - start)
        nonce = secrets.token_hex(16)
        with self.index.begin() as db:
            _lock(db)
            self._check_free(db, robot, start, end, None)
            self._check_limits(db, user, start, end - start, None)
            result = db.execute(
                sa.insert(reservations).values(
                    robot=robot,
                    user=user,
                    start=start,
                    end=end,
                    booked_end=end,
                    created=now,
                    released=None,
                    nonce=nonce,
                )
            )
            key = result.inserted_primary_key
            assert key is not None
            row = db.execute(sa.select(reservations).where(R.id == int(key[0]))).one()
        booked = _reservation(row)
        log.info(
            "reservation %d: %s booked %s from %s to %s",
            booked.id,
            user,
            robot,
            when(start),
            when(end),
        )
        return Booking(booked, self._key(booked.id, nonce))

    def extend(self, user: str, reservation_id: int, end: float) -> Reservation:
        """Make a slot end later, if the time after it is free and the rules allow."""
        now = self.index.clock()
        with self.index.begin() as db:
            _lock(db)
            found = self._mine(db, user, reservation_id, "extend it")
            if found.released is not None:
                raise ReservationError(
                    f"reservation {found.id} was released; book a new slot instead"
                )
            if now >= found.end:
                raise ReservationError(
                    f"reservation {found.id} ended at {when(found.end)}; book a new slot"
                )
            self._check_times(now, found.start, end)
            if end <= found.end:
                raise ReservationError(
                    f"an extension must end after the slot's end, {when(found.end)}"
                )
            self._check_length(end - found.start, extending=True)
            self._check_free(db, found.robot, found.end, end, found.id, extending=True)
            self._check_limits(db, user, found.start, end - found.start, found.id)
            db.execute(
                sa.update(reservations).where(R.id == found.id).values(end=end, booked_end=end)
            )
            row = db.execute(sa.select(reservations).where(R.id == found.id)).one()
        log.info("reservation %d extended to %s", found.id, when(end))
        return _reservation(row)

    def release(self, user: str, reservation_id: int) -> Reservation:
        """End a slot now (cancel it, before it began): the rest is free for others."""
        now = self.index.clock()
        with self.index.begin() as db:
            _lock(db)
            found = self._mine(db, user, reservation_id, "release it")
            if found.released is not None:
                raise ReservationError(
                    f"reservation {found.id} was released already, at {when(found.released)}"
                )
            if now >= found.end:
                raise ReservationError(
                    f"reservation {found.id} ended at {when(found.end)}; nothing to release"
                )
            end = max(found.start, now)
            db.execute(
                sa.update(reservations).where(R.id == found.id).values(end=end, released=now)
            )
            row = db.execute(sa.select(reservations).where(R.id == found.id)).one()
        log.info("reservation %d released at %s", found.id, when(now))
        return _reservation(row)

    # -- reading ------------------------------------------------------------------------

    def get(self, reservation_id: int) -> Reservation:
        with self.index.engine.connect() as db:
            row = db.execute(sa.select(reservations).where(R.id == reservation_id)).first()
        if row is None:
            raise RecordNotFound("reservation", str(reservation_id))
        return _reservation(row)

    def find(
        self,
        *,
        robot: str | None = None,
        user: str | None = None,
        since: float | None = None,
        until: float | None = None,
        released: bool = False,
        limit: int = 500,
    ) -> list[Reservation]:
        """Slots that end after ``since`` and start before ``until``, by start time.

        Released slots are left out unless ``released``; a slot released before it
        began never shows (it took no time).
        """
        query = sa.select(reservations)
        if robot is not None:
            query = query.where(R.robot == robot)
        if user is not None:
            query = query.where(R.user == user)
        if since is not None:
            query = query.where(R.end > since)
        if until is not None:
            query = query.where(R.start < until)
        if not released:
            query = query.where(R.released.is_(None))
        query = query.where(R.end > R.start).order_by(R.start, R.id).limit(limit)
        with self.index.engine.connect() as db:
            return [_reservation(r) for r in db.execute(query)]

    def current(self, user: str, robot: str) -> Reservation | None:
        """``user``'s slot of ``robot`` that runs now, if any."""
        now = self.index.clock()
        found = self.find(robot=robot, user=user, since=now, until=now + 1e-6, limit=1)
        return found[0] if found else None

    def key(self, user: str, reservation_id: int) -> str:
        """The key of one of ``user``'s reservations (NotYourReservation for others')."""
        with self.index.engine.connect() as db:
            row = db.execute(sa.select(reservations).where(R.id == reservation_id)).first()
        if row is None:
            raise RecordNotFound("reservation", str(reservation_id))
        if row.user != user:
            raise NotYourReservation(reservation_id, row.user, "read its key")
        return self._key(row.id, row.nonce)

    # -- keys ---------------------------------------------------------------------------

    def authorize(self, key: str, robot: str | None = None) -> Access:
        """What ``key`` opens now (on ``robot``, if given); KeyRefused saying why not."""
        reservation_id, mac = _parse(key)
        with self.index.engine.connect() as db:
            row = db.execute(sa.select(reservations).where(R.id == reservation_id)).first()
        if row is None or not hmac.compare_digest(mac, self._mac(row.id, row.nonce)):
            raise UnknownKey()
        found = _reservation(row)
        now = self.index.clock()
        if robot is not None and found.robot != robot:
            raise KeyRefused(f"this key is for {found.robot}, not {robot}")
        if found.released is not None:
            raise KeyRefused(
                f"this key's slot on {found.robot} was released at {when(found.released)};"
                " book another slot"
            )
        if now < found.start:
            raise KeyRefused(
                f"this key's slot on {found.robot} starts at {when(found.start)}, in"
                f" {duration(found.start - now)}; connect then"
            )
        if now >= found.end:
            raise KeyRefused(
                f"this key's slot on {found.robot} ended at {when(found.end)}; book another slot"
            )
        return Access(found, found.end - now)

    def _mac(self, reservation_id: int, nonce: str) -> str:
        digest = hmac.new(
            self._secret, f"labd reservation {reservation_id} {nonce}".encode(), hashlib.sha256
        ).digest()
        return base64.urlsafe_b64encode(digest).decode().rstrip("=")

    def _key(self, reservation_id: int, nonce: str) -> str:
        return f"{KEY_PREFIX}{reservation_id}_{self._mac(reservation_id, nonce)}"

    # -- rules --------------------------------------------------------------------------

    def _check_times(self, now: float, start: float, end: float) -> None:
        """Refuse times no rule could allow before any rule formats them: not numbers,
        more than a year ago, or past the latest end a booking may have now."""
        rules = self.rules
        latest = now + rules.horizon + rules.max_slot
        for at in (start, end):
            if not math.isfinite(at):
                raise ReservationError("give the slot's start and end as times")
            if at < now - MAX_HORIZON:
                raise ReservationError(
                    f"the slot's times are more than a year in the past (it is {when(now)}"
                    " now); book a time from now on"
                )
            if at > latest:
                raise ReservationError(
                    f"a slot may start at most {duration(rules.horizon)} ahead and last at"
                    f" most {duration(rules.max_slot)}, so it ends by {when(latest)}; this"
                    f" one would end at {when(end)}: book an earlier or shorter slot"
                )

    def _check_length(self, seconds: float, *, extending: bool = False) -> None:
        if seconds > self.rules.max_slot:
            what = "extended, the slot would last" if extending else "this one lasts"
            raise ReservationError(
                f"a slot may last at most {duration(self.rules.max_slot)} here; {what}"
                f" {duration(seconds)}: book a shorter slot, or two"
            )

    def _mine(self, db: Connection, user: str, reservation_id: int, action: str) -> Reservation:
        row = db.execute(sa.select(reservations).where(R.id == reservation_id)).first()
        if row is None:
            raise RecordNotFound("reservation", str(reservation_id))
        if row.user != user:
            raise NotYourReservation(reservation_id, row.user, action)
        return _reservation(row)

    def _check_free(
        self,
        db: Connection,
        robot: str,
        start: float,
        end: float,
        exclude: int | None,
        *,
        extending: bool = False,
    ) -> None:
        query = sa.select(reservations).where(
            R.robot == robot, R.start < end, R.end > start, R.end > R.start
        )
        if exclude is not None:
            query = query.where(R.id != exclude)
        row = db.execute(query.order_by(R.start).limit(1)).first()
        if row is None:
            return
        if extending:
            message = (
                f"the next slot of {robot} is booked by {row.user} from {when(row.start)};"
                f" you may extend until then at most"
            )
        else:
            message = (
                f"{robot} is booked from {when(row.start)} to {when(row.end)} by {row.user};"
                f" choose a slot that ends by {when(row.start)} or starts at {when(row.end)}"
                " or later (the calendar shows the free times)"
            )
        raise SlotTaken(robot, message)

    def _check_limits(
        self, db: Connection, user: str, start: float, seconds: float, exclude: int | None
    ) -> None:
        rules = self.rules
        day = _day_start(start)
        week = day - moment(day).weekday() * DAY
        for first, span, most_slots, most_minutes, name in (
            (day, DAY, rules.max_slots_per_day, rules.max_minutes_per_day, "day"),
            (week, 7 * DAY, rules.max_slots_per_week, rules.max_minutes_per_week, "week"),
        ):
            if most_slots is None and most_minutes is None:
                continue
            query = sa.select(sa.func.count(), sa.func.coalesce(sa.func.sum(R.end - R.start), 0.0))
            query = query.where(
                R.user == user, R.start >= first, R.start < first + span, R.end > R.start
            )
            if exclude is not None:
                query = query.where(R.id != exclude)
            slots, used = db.execute(query).one()
            period = (
                f"on {moment(first):%Y-%m-%d} (UTC)"
                if name == "day"
                else f"in the week of {moment(first):%Y-%m-%d} (UTC)"
            )
            if most_slots is not None and slots + 1 > most_slots:
                raise OverLimit(
                    f"{user} has {slots} slots {period}, the most a {name} allows here"
                    f" ({most_slots}); release one, or book another {name}"
                )
            total = (float(used) + seconds) / 60
            if most_minutes is not None and total > most_minutes + 1e-9:
                left = max(0.0, most_minutes - float(used) / 60)
                raise OverLimit(
                    f"this slot would give {user} {total:.0f} min of slots {period}, over"
                    f" the {most_minutes:g} min a {name} allows here; {left:.0f} min are left"
                )


def load_secret(path: Path) -> bytes:
    """A secret of the lab's (reservation keys, held-out suites' seeds), made (readable
    by its owner only) if new."""
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        path.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
        try:
            fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        except FileExistsError:  # another process made it meanwhile
            return path.read_bytes()
        data = secrets.token_bytes(SECRET_BYTES)
        with os.fdopen(fd, "wb") as out:
            out.write(data)
    if len(data) < 16:
        raise ReservationError(f"{path} is not a secret of the lab's (too short); remove it")
    return data


def _lock(db: Connection) -> None:
    """On PostgreSQL, hold the reservations' lock until the transaction ends (SQLite's
    write transactions already run one at a time)."""
    if db.dialect.name == "postgresql":
        db.execute(sa.text("SELECT pg_advisory_xact_lock(hashtext('labd:reservations'))"))


def rekey(db: Connection, user: str, now: float) -> int:
    """Give ``user``'s slots that have not ended new nonces, in the transaction ``db``:
    every key made for them so far opens nothing (the slots stay booked; their owner
    fetches the new keys). How many slots were re-keyed."""
    rows = db.execute(
        sa.select(R.id).where(R.user == user, R.end > now, R.released.is_(None))
    ).all()
    for (reservation_id,) in rows:
        db.execute(
            sa.update(reservations)
            .where(R.id == reservation_id)
            .values(nonce=secrets.token_hex(16))
        )
    return len(rows)


def _parse(key: str) -> tuple[int, str]:
    """The reservation's number and the MAC of a key shaped exactly as the lab makes
    them (``MalformedKey`` for anything else: other digits, letters, lengths)."""
    found = KEY.fullmatch(key)
    if found is None:
        raise MalformedKey()
    return int(found.group(1)), found.group(2)


def _reservation(row: Any) -> Reservation:
    return Reservation(
        id=row.id,
        robot=row.robot,
        user=row.user,
        start=row.start,
        end=row.end,
        booked_end=row.booked_end,
        created=row.created,
        released=row.released,
    )


def _day_start(seconds: float) -> float:
    return math.floor(seconds / DAY) * DAY


def when(seconds: float) -> str:
    """A time as people read it in messages: ``2026-05-01 10:00:30 UTC`` (a time out of
    the calendar's years 1 to 9999 says so, rather than failing the message)."""
    try:
        return f"{moment(seconds):%Y-%m-%d %H:%M:%S} UTC"
    except (OverflowError, OSError, ValueError):
        return f"{seconds:.6g} s from 1970 (out of the calendar)"


def duration(seconds: float) -> str:
    """``90 s``, ``45 min``, ``2 h 30 min``, ``14 days``."""
    if seconds < 120:
        return f"{seconds:.0f} s"
    minutes = round(seconds / 60)
    if minutes < 120:
        return f"{minutes} min"
    if minutes % (24 * 60) == 0:
        days = minutes // (24 * 60)
        return f"{days} day" if days == 1 else f"{days} days"
    hours, rest = divmod(minutes, 60)
    return f"{hours} h {rest} min" if rest else f"{hours} h"
