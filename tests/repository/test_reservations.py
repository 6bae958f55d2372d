"""Reservations on both databases, with a clock the test moves: every rule enforced,
keys that open one robot for one slot, and racing bookings of which exactly one wins."""

from __future__ import annotations

import datetime as dt
import threading

import pytest
import sqlalchemy as sa

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
from repository.index import Index, connect
from repository.reservations import Booking, Reservations, Rules, load_secret, rekey, when
from tests.fakes import WallClock

# Monday 2030-01-07 09:00 UTC: tests start on a known day of a known week.
MONDAY = dt.datetime(2030, 1, 7, 9, 0, tzinfo=dt.UTC).timestamp()
MIN = 60.0
HOUR = 3600.0
SECRET = b"s" * 32


@pytest.fixture
def clock() -> WallClock:
    return WallClock(MONDAY)


@pytest.fixture
def clocked_index(database_url, clock):
    """The index on ``clock``, alice and bob in it."""
    index = Index(connect(database_url), clock=clock)
    index.create()
    for name in ("alice", "bob"):
        index.add_user(name)
    yield index
    index.close()


def booked(clocked_index, **rules):
    return Reservations(clocked_index, Rules(**rules), SECRET)


@pytest.fixture
def desk(clocked_index):
    return booked(clocked_index)


def test_a_booking_gives_a_key_for_its_robot_and_its_slot_only(desk, clock):
    """A key opens its robot from its slot's start to its end, with the seconds left;
    before, after, on another robot, or forged, it is refused saying why."""
    made = desk.book("alice", "icreate-1", MONDAY + HOUR, MONDAY + 2 * HOUR)
    key = made.key
    with pytest.raises(KeyRefused, match=r"starts at 2030-01-07 10:00:00 UTC, in 60 min"):
        desk.authorize(key, "icreate-1")
    clock.now = MONDAY + HOUR
    access = desk.authorize(key, "icreate-1")
    assert access.seconds == HOUR and access.reservation.user == "alice"
    assert desk.authorize(key).seconds == HOUR  # an outside authorizer names no robot
    with pytest.raises(KeyRefused, match="this key is for icreate-1, not pr2-1"):
        desk.authorize(key, "pr2-1")
    clock.now = MONDAY + 2 * HOUR - 1
    assert desk.authorize(key, "icreate-1").seconds == 1
    clock.now = MONDAY + 2 * HOUR
    with pytest.raises(KeyRefused, match=r"ended at 2030-01-07 11:00:00 UTC; book another"):
        desk.authorize(key, "icreate-1")
    clock.now = MONDAY + HOUR + 1
    forged = key[:-4] + ("AAAA" if not key.endswith("AAAA") else "BBBB")
    for bad in (forged, "labd_rk_999_" + "A" * 43):
        with pytest.raises(UnknownKey, match="the lab knows no such key"):
            desk.authorize(bad, "icreate-1")
    for bad in ("labd_rk_999_abc", "nonsense", "", key + "x"):
        with pytest.raises(MalformedKey, match="this is not a key of this lab"):
            desk.authorize(bad, "icreate-1")


@pytest.mark.parametrize(
    "spelling",
    [
        "labd_rk_{n}_١٢٣",  # Arabic-Indic digits where the MAC goes
        "labd_rk_²_{mac}",  # a superscript two: isdigit() says yes, int() says no
        "labd_rk_{fullwidth}_{mac}",  # the reservation's number in fullwidth digits
        "labd_rk_{arabic}_{mac}",  # ... and in Arabic-Indic ones
        "labd_rk_{n}_{mac}\n",  # a newline after it
        "labd_rk_0{n}_{mac}",  # a leading zero
        "labd_rk_{n}_{mac_e}",  # one letter of the MAC outside ASCII
    ],
)
def test_a_key_is_parsed_strictly(desk, clock, spelling):
    """Only the exact ASCII shape of a key is looked at: any other digits or letters,
    even where int() would read the same number, are MalformedKey, never a crash."""
    made = desk.book("alice", "icreate-1", MONDAY, MONDAY + HOUR)
    n = str(made.reservation.id)
    mac = made.key.rsplit("_", 1)[1]
    odd = spelling.format(
        n=n,
        mac=mac,
        mac_e=mac[:-1] + "é",
        fullwidth="".join(chr(0xFF10 + int(d)) for d in n),  # FULLWIDTH DIGIT ...
        arabic="".join(chr(0x0660 + int(d)) for d in n),  # ARABIC-INDIC DIGIT ...
    )
    with pytest.raises(MalformedKey):
        desk.authorize(odd, "icreate-1")
    assert desk.authorize(made.key, "icreate-1").seconds == HOUR


def test_rekeying_a_person_ends_their_keys_and_keeps_their_slots(clocked_index, desk, clock):
    """``rekey`` (a revoked person) makes every key of their current and coming slots
    open nothing; the slots stay booked, their new keys work, others' keys are untouched."""
    now_slot = desk.book("alice", "icreate-1", MONDAY, MONDAY + HOUR)
    later = desk.book("alice", "pr2-1", MONDAY + 2 * HOUR, MONDAY + 3 * HOUR)
    bobs = desk.book("bob", "pr2-1", MONDAY, MONDAY + HOUR)
    with clocked_index.begin() as db:
        assert rekey(db, "alice", clock.now) == 2
    for old in (now_slot, later):
        with pytest.raises(UnknownKey):
            desk.authorize(old.key)
    assert desk.authorize(desk.key("alice", now_slot.reservation.id)).seconds == HOUR
    assert desk.authorize(bobs.key).seconds == HOUR
    assert [r.id for r in desk.find(user="alice")] == [
        now_slot.reservation.id,
        later.reservation.id,
    ]


@pytest.mark.parametrize(
    ("start", "end", "message"),
    [
        (MONDAY, MONDAY - 1e300, "more than a year in the past"),
        (MONDAY, MONDAY + 1e12, "ends by 2030-01-21 10:00:00 UTC"),
        (MONDAY, MONDAY + 1e300, "out of the calendar"),
        (253402300740.0, 253402302540.0, "at most 14 days ahead"),  # 9999-12-31 23:59
        (-62135596800.0, MONDAY, "more than a year in the past"),  # the year 1
        (MONDAY, float("inf"), "as times"),
    ],
)
def test_times_out_of_the_calendar_are_refused_saying_why(desk, clock, start, end, message):
    """A booking or an extension with a time out of any calendar (year 9999, 10^12 s,
    -10^300) is a ReservationError naming the span allowed, never an OverflowError."""
    with pytest.raises(ReservationError, match=message):
        desk.book("alice", "icreate-1", start, end)
    made = desk.book("alice", "icreate-1", MONDAY, MONDAY + 30 * MIN)
    with pytest.raises(ReservationError):
        desk.extend("alice", made.reservation.id, end)
    assert when(1e300) == "1e+300 s from 1970 (out of the calendar)"


def test_the_operator_cannot_set_an_unbounded_horizon_or_slot():
    """Rules refuse a horizon over a year and a slot over a day (so every booking's
    times are dates people can read)."""
    with pytest.raises(ValueError, match="at most 365 days ahead"):
        Rules(horizon=366 * 86400)
    with pytest.raises(ValueError, match=r"at most 1 day$"):
        Rules(max_slot=86400 + 1)
    assert Rules(horizon=365 * 86400, max_slot=86400).horizon == 365 * 86400


def test_keys_are_not_in_the_database_and_another_secret_opens_nothing(clocked_index, desk, clock):
    """The database holds no key (a copy of it opens no robot); a lab with another
    secret refuses the key; the owner can read their key again, others cannot."""
    made = desk.book("alice", "icreate-1", MONDAY, MONDAY + HOUR)
    with clocked_index.engine.connect() as db:
        rows = [tuple(map(str, r)) for r in db.execute(sa.text("SELECT * FROM reservations"))]
    assert all(made.key not in value and made.key[-20:] not in value for r in rows for value in r)
    assert desk.key("alice", made.reservation.id) == made.key
    with pytest.raises(NotYourReservation, match="alice's; only they may read its key"):
        desk.key("bob", made.reservation.id)
    other = Reservations(clocked_index, Rules(), b"t" * 32)
    with pytest.raises(KeyRefused, match="no such key"):
        other.authorize(made.key, "icreate-1")


def test_slots_in_the_past_of_no_length_too_long_or_too_far_are_refused(desk, clock):
    """Each bad slot is refused with what to change."""
    cases = [
        (MONDAY - HOUR, MONDAY - 1, "in the past"),
        (MONDAY + HOUR, MONDAY + HOUR, "must end after it starts"),
        (MONDAY + HOUR, MONDAY + HOUR - 60, "must end after it starts"),
        (MONDAY, MONDAY + 2 * HOUR, "at most 60 min here; this one lasts 2 h"),
        (MONDAY + 15 * 86400, MONDAY + 15 * 86400 + 60, "at most 14 days ahead"),
        (float("nan"), MONDAY, "as times"),
    ]
    for start, end, message in cases:
        with pytest.raises(ReservationError, match=message):
            desk.book("alice", "icreate-1", start, end)
    assert desk.find() == []


def test_a_slot_asked_for_a_moment_ago_starts_now(desk, clock):
    """A request for 'now' arrives a little later: its slot starts when it arrives."""
    made = desk.book("alice", "icreate-1", MONDAY - 5, MONDAY + 10 * MIN)
    assert made.reservation.start == MONDAY


def test_slots_of_one_robot_never_overlap(clocked_index):
    """An overlapping booking is refused naming the slot in the way; touching slots and
    other robots are fine."""
    desk = booked(clocked_index, max_minutes_per_day=None)
    desk.book("alice", "icreate-1", MONDAY + HOUR, MONDAY + 2 * HOUR)
    with pytest.raises(SlotTaken, match=r"booked from 2030-01-07 10:00:00 UTC to .* by alice"):
        desk.book("bob", "icreate-1", MONDAY + 90 * MIN, MONDAY + 150 * MIN)
    with pytest.raises(SlotTaken):
        desk.book("bob", "icreate-1", MONDAY + 30 * MIN, MONDAY + 61 * MIN)
    desk.book("bob", "icreate-1", MONDAY + 2 * HOUR, MONDAY + 3 * HOUR)  # starts at its end
    desk.book("bob", "icreate-1", MONDAY, MONDAY + HOUR)  # ends at its start
    desk.book("bob", "pr2-1", MONDAY + HOUR, MONDAY + 2 * HOUR)  # another robot
    assert [(r.user, r.robot) for r in desk.find(robot="icreate-1")] == [
        ("bob", "icreate-1"),
        ("alice", "icreate-1"),
        ("bob", "icreate-1"),
    ]


def test_limits_per_day_and_per_week(clocked_index, clock):
    """A person's slots and minutes per UTC day and per ISO week are capped."""
    desk = booked(
        clocked_index,
        max_slots_per_day=2,
        max_minutes_per_day=90,
        max_slots_per_week=3,
        max_minutes_per_week=None,
        max_slot=2 * HOUR,
    )
    desk.book("alice", "icreate-1", MONDAY, MONDAY + 30 * MIN)
    with pytest.raises(OverLimit, match=r"give alice 100 min of slots on 2030-01-07 .* 60 min"):
        desk.book("alice", "pr2-1", MONDAY + HOUR, MONDAY + HOUR + 70 * MIN)
    desk.book("alice", "pr2-1", MONDAY + HOUR, MONDAY + 2 * HOUR)
    with pytest.raises(OverLimit, match=r"alice has 2 slots on 2030-01-07 \(UTC\), the most"):
        desk.book("alice", "pr2-1", MONDAY + 3 * HOUR, MONDAY + 3 * HOUR + MIN)
    desk.book("bob", "pr2-1", MONDAY + 3 * HOUR, MONDAY + 3 * HOUR + MIN)  # bob's own count
    tuesday = MONDAY + 86400
    desk.book("alice", "icreate-1", tuesday, tuesday + 10 * MIN)
    with pytest.raises(OverLimit, match=r"3 slots in the week of 2030-01-07"):
        desk.book("alice", "icreate-1", tuesday + HOUR, tuesday + HOUR + 10 * MIN)
    next_monday = MONDAY + 7 * 86400
    desk.book("alice", "icreate-1", next_monday, next_monday + 10 * MIN)  # a new week


def test_minutes_per_week(clocked_index):
    """Minutes per week are summed over the week's days."""
    desk = booked(clocked_index, max_minutes_per_week=100, max_slots_per_day=None)
    for day in range(2):
        start = MONDAY + day * 86400
        desk.book("alice", "icreate-1", start, start + 50 * MIN)
    with pytest.raises(OverLimit, match=r"over the 100 min a week allows here; 0 min are left"):
        desk.book("alice", "icreate-1", MONDAY + 2 * 86400, MONDAY + 2 * 86400 + MIN)


def test_an_extension_only_into_free_time_and_within_the_rules(desk, clock):
    """A slot extends if the time after it is free and the longer slot keeps to the
    rules; not someone else's, not after it ended, not past the next booking."""
    mine = desk.book("alice", "icreate-1", MONDAY, MONDAY + 20 * MIN).reservation
    desk.book("bob", "icreate-1", MONDAY + 40 * MIN, MONDAY + HOUR)
    longer = desk.extend("alice", mine.id, MONDAY + 40 * MIN)
    assert longer.end == MONDAY + 40 * MIN
    with pytest.raises(SlotTaken, match="booked by bob from 2030-01-07 09:40:00 UTC; you may"):
        desk.extend("alice", mine.id, MONDAY + 45 * MIN)
    with pytest.raises(NotYourReservation, match="only they may extend it"):
        desk.extend("bob", mine.id, MONDAY + 41 * MIN)
    with pytest.raises(ReservationError, match="must end after the slot's end"):
        desk.extend("alice", mine.id, MONDAY + 30 * MIN)
    lone = desk.book("alice", "pr2-1", MONDAY, MONDAY + 50 * MIN).reservation
    with pytest.raises(ReservationError, match="extended, the slot would last 70 min"):
        desk.extend("alice", lone.id, MONDAY + 70 * MIN)
    clock.now = MONDAY + 50 * MIN
    with pytest.raises(ReservationError, match=r"ended at .*; book a new slot"):
        desk.extend("alice", lone.id, MONDAY + 55 * MIN)
    with pytest.raises(RecordNotFound):
        desk.extend("alice", 999, MONDAY + 55 * MIN)


def test_an_extension_counts_against_the_limits(clocked_index):
    """Extending cannot get around the minutes a day allows."""
    desk = booked(clocked_index, max_minutes_per_day=60)
    mine = desk.book("alice", "icreate-1", MONDAY, MONDAY + 30 * MIN).reservation
    desk.book("alice", "pr2-1", MONDAY + HOUR, MONDAY + HOUR + 20 * MIN)
    with pytest.raises(OverLimit, match="70 min of slots"):
        desk.extend("alice", mine.id, MONDAY + 50 * MIN)
    assert desk.extend("alice", mine.id, MONDAY + 40 * MIN).end == MONDAY + 40 * MIN


def test_an_early_release_frees_the_rest_and_ends_the_key(desk, clock):
    """Releasing ends the slot now: someone else can book the rest, the key stops
    working, the used part stays in the calendar, and the limits count only that part."""
    made = desk.book("alice", "icreate-1", MONDAY, MONDAY + HOUR)
    clock.now = MONDAY + 10 * MIN
    assert desk.authorize(made.key, "icreate-1").seconds == 50 * MIN
    released = desk.release("alice", made.reservation.id)
    assert released.end == MONDAY + 10 * MIN and released.booked_end == MONDAY + HOUR
    with pytest.raises(KeyRefused, match="was released at 2030-01-07 09:10:00 UTC"):
        desk.authorize(made.key, "icreate-1")
    desk.book("bob", "icreate-1", MONDAY + 10 * MIN, MONDAY + HOUR)
    with pytest.raises(ReservationError, match="released already"):
        desk.release("alice", made.reservation.id)
    assert [r.user for r in desk.find(robot="icreate-1", released=True)] == ["alice", "bob"]
    assert [r.user for r in desk.find(robot="icreate-1")] == ["bob"]


def test_a_release_before_the_start_cancels_and_others_cannot_release(desk, clock):
    """Released before it begins, a slot takes no time at all; only its owner releases."""
    made = desk.book("alice", "icreate-1", MONDAY + HOUR, MONDAY + 2 * HOUR)
    with pytest.raises(NotYourReservation, match="only they may release it"):
        desk.release("bob", made.reservation.id)
    cancelled = desk.release("alice", made.reservation.id)
    assert cancelled.seconds == 0 and cancelled.state(clock.now) == "released"
    assert desk.find(released=True) == []
    desk.book("bob", "icreate-1", MONDAY + HOUR, MONDAY + 2 * HOUR)


def test_a_replayed_key_of_an_earlier_slot_opens_nothing_in_a_later_one(desk, clock):
    """Alice's key of her ended slot does not open the robot in Bob's slot after it."""
    alice = desk.book("alice", "icreate-1", MONDAY, MONDAY + 10 * MIN)
    bob = desk.book("bob", "icreate-1", MONDAY + 10 * MIN, MONDAY + 20 * MIN)
    clock.now = MONDAY + 15 * MIN
    with pytest.raises(KeyRefused, match="ended"):
        desk.authorize(alice.key, "icreate-1")
    assert desk.authorize(bob.key, "icreate-1").reservation.user == "bob"
    assert desk.current("bob", "icreate-1").id == bob.reservation.id
    assert desk.current("alice", "icreate-1") is None


@pytest.mark.parametrize("rounds", [5])
def test_racing_overlapping_bookings_exactly_one_wins(clocked_index, database_url, rounds):
    """Two clients book overlapping slots at the same moment, from their own
    connections: each time exactly one wins and the other is told the slot is taken."""
    # no daily limit: whoever wins every round must not run into one and win by refusal
    rules = {"max_slots_per_day": None, "max_minutes_per_day": None}
    desks = [
        booked(Index(connect(database_url), clock=clocked_index.clock), **rules) for _ in range(2)
    ]
    try:
        for n in range(rounds):
            start = MONDAY + n * HOUR
            barrier = threading.Barrier(2)
            results: list[object] = [None, None]

            def book(
                i: int,
                start: float = start,
                barrier: threading.Barrier = barrier,
                results: list[object] = results,
            ) -> None:
                user = ("alice", "bob")[i]
                barrier.wait()
                try:
                    results[i] = desks[i].book(user, "icreate-1", start + i * MIN, start + 30 * MIN)
                except Exception as err:  # SlotTaken for the loser; anything else is shown below
                    results[i] = err

            threads = [threading.Thread(target=book, args=(i,)) for i in range(2)]
            for t in threads:
                t.start()
            for t in threads:
                t.join(30)
            won = [r for r in results if isinstance(r, Booking)]
            lost = [r for r in results if isinstance(r, SlotTaken)]
            assert len(won) == 1 and len(lost) == 1, results
        assert len(desks[0].find(robot="icreate-1")) == rounds
    finally:
        for desk in desks:
            desk.index.close()


def test_racing_bookings_of_one_person_keep_to_their_limit(clocked_index, database_url):
    """Two bookings of different robots by one person, at once, with room for one more
    slot that day: exactly one is accepted."""
    desks = [
        booked(Index(connect(database_url), clock=clocked_index.clock), max_slots_per_day=1)
        for _ in range(2)
    ]
    barrier = threading.Barrier(2)
    results: list[object] = [None, None]

    def book(i: int) -> None:
        barrier.wait()
        try:
            results[i] = desks[i].book("alice", ("icreate-1", "pr2-1")[i], MONDAY, MONDAY + MIN)
        except OverLimit as err:
            results[i] = err

    threads = [threading.Thread(target=book, args=(i,)) for i in range(2)]
    try:
        for t in threads:
            t.start()
        for t in threads:
            t.join(30)
        assert sum(isinstance(r, OverLimit) for r in results) == 1, results
    finally:
        for desk in desks:
            desk.index.close()


def test_the_secret_is_made_once_and_kept_private(tmp_path):
    """The secret file is made on first use, readable by its owner only, and kept."""
    path = tmp_path / "keys" / "reservations.secret"
    first = load_secret(path)
    assert len(first) == 32 and load_secret(path) == first
    assert path.stat().st_mode & 0o777 == 0o600
    path.write_bytes(b"short")
    with pytest.raises(ReservationError, match="too short"):
        load_secret(path)
