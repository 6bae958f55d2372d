"""Reservations, keys, calendars, the authorizer and tokens through the HTTP API, in
process, on both databases, with a clock the test moves: every rule refused with a
message a person can act on, and every answer declared in the OpenAPI document."""

from __future__ import annotations

import datetime as dt

import httpx
import pytest
from icalendar import Calendar

from labd.api.app import create_app
from labd.service import Service, ServiceConfig
from repository.reservations import Rules
from tests.labd.test_api import check_declared

MONDAY = dt.datetime(2030, 1, 7, 9, 0, tzinfo=dt.UTC)
ROBOTS = ("icreate-1", "pr2-1")


class Clock:
    def __init__(self) -> None:
        self.now = MONDAY.timestamp()

    def __call__(self) -> float:
        return self.now

    def at(self, minutes: float) -> str:
        return (MONDAY + dt.timedelta(minutes=minutes)).isoformat()


@pytest.fixture
def clock():
    return Clock()


@pytest.fixture
def service(tmp_path, sqlite_url, clock):
    rules = Rules(max_slot=3600, max_slots_per_day=3, max_minutes_per_day=120)
    config = ServiceConfig(data=tmp_path / "data", database=sqlite_url, workers=0, rules=rules)
    service = Service(config, clock=clock)
    yield service
    service.index.close()


@pytest.fixture
async def api(service):
    changed = []
    app = create_app(service, robots=ROBOTS, on_reservation=changed.append)
    seen: list[httpx.Response] = []

    async def keep(response):
        await response.aread()
        seen.append(response)

    async with httpx.AsyncClient(
        transport=httpx.ASGITransport(app=app, client=("203.0.113.5", 4000)),
        base_url="http://lab.test",
        event_hooks={"response": [keep]},
    ) as client:
        client.changed = changed
        client.app = app
        yield client
    check_declared(app.openapi(), seen)


@pytest.fixture
def people(service):
    return {name: service.index.add_user(name) for name in ("alice", "bob")}


def auth(token):
    return {"Authorization": f"Bearer {token}"}


async def book(api, token, robot="icreate-1", **body):
    return await api.post("/api/reservations", json={"robot": robot, **body}, headers=auth(token))


async def test_booking_gives_a_key_that_only_its_owner_reads(api, people, clock):
    """A booking answers 201 with the slot and its key; the list and the slot show who
    and when, never the key; only the owner reads the key again."""
    made = await book(api, people["alice"], start=clock.at(60), minutes=30)
    assert made.status_code == 201, made.text
    body = made.json()
    slot = body["reservation"]
    assert (slot["robot"], slot["user"], slot["state"], slot["minutes"]) == (
        "icreate-1",
        "alice",
        "upcoming",
        30,
    )
    assert made.headers["cache-control"] == "no-store"
    key = body["key"]["key"]
    assert body["key"]["path"] == "/robots/icreate-1" and body["key"]["seconds"] == 0
    listed = await api.get("/api/reservations", params={"robot": "icreate-1"})
    assert [r["user"] for r in listed.json()["reservations"]] == ["alice"]
    assert key not in listed.text
    assert key not in (await api.get(f"/api/reservations/{slot['id']}")).text
    again = await api.get(f"/api/reservations/{slot['id']}/key", headers=auth(people["alice"]))
    assert again.json()["key"] == key
    other = await api.get(f"/api/reservations/{slot['id']}/key", headers=auth(people["bob"]))
    assert other.status_code == 403
    assert (
        other.json()["error"] == f"reservation {slot['id']} is alice's; only they may read its key"
    )
    anonymous = await api.get(f"/api/reservations/{slot['id']}/key")
    assert (
        anonymous.status_code == 401 and "needs a token or a sign-in" in anonymous.json()["error"]
    )


@pytest.mark.parametrize(
    ("body", "status", "message"),
    [
        ({"start": "2030-01-07T08:00:00Z", "minutes": 30}, 422, "in the past"),
        ({"minutes": 0}, 422, "must end after it starts"),
        ({"minutes": -5}, 422, "must end after it starts"),
        ({"start": "2030-01-07T10:00:00", "end": "2030-01-07T09:30:00"}, 422, "must end after"),
        ({"minutes": 90}, 422, "at most 60 min here; this one lasts 90 min"),
        ({"start": "2030-02-07T10:00:00Z", "minutes": 10}, 422, "at most 14 days ahead"),
        ({"minutes": 10, "end": "2030-01-07T10:00:00Z"}, 422, "give the slot's end or its"),
        ({"robot": "r2d2", "minutes": 10}, 404, "no live robot 'r2d2' here; the robots"),
        ({"minutes": 10, "colour": "red"}, 422, "colour"),
    ],
)
async def test_bad_slots_are_refused_saying_what_to_change(api, people, body, status, message):
    """Each bad booking is refused with its status and a message naming the rule."""
    reply = await api.post(
        "/api/reservations", json={"robot": "icreate-1", **body}, headers=auth(people["alice"])
    )
    assert reply.status_code == status, reply.text
    assert message in reply.json()["error"]


async def test_overlap_and_limits(api, people, clock):
    """An overlapping slot is a 409 naming who has it and the free times; a slot over
    the day's limits is a 429 saying what is left."""
    assert (await book(api, people["alice"], minutes=60)).status_code == 201
    taken = await book(api, people["bob"], start=clock.at(30), minutes=60)
    assert taken.status_code == 409
    assert taken.json()["error"] == (
        "icreate-1 is booked from 2030-01-07 09:00:00 UTC to 2030-01-07 10:00:00 UTC by alice;"
        " choose a slot that ends by 2030-01-07 09:00:00 UTC or starts at 2030-01-07"
        " 10:00:00 UTC or later (the calendar shows the free times)"
    )
    assert (await book(api, people["alice"], "pr2-1", start=clock.at(60), minutes=50)).is_success
    over = await book(api, people["alice"], "pr2-1", start=clock.at(120), minutes=20)
    assert over.status_code == 429
    assert "over the 120 min a day allows here; 10 min are left" in over.json()["error"]


async def test_extend_and_release(api, people, clock):
    """An extension into free time works and is told to the bridge; into someone's slot
    it is a 409; a release ends the slot now, frees the rest, and is told to the bridge;
    nobody changes another's slot."""
    mine = (await book(api, people["alice"], minutes=20)).json()["reservation"]
    await book(api, people["bob"], start=clock.at(40), minutes=20)
    path = f"/api/reservations/{mine['id']}"
    longer = await api.post(f"{path}/extend", json={"minutes": 20}, headers=auth(people["alice"]))
    assert longer.status_code == 200 and longer.json()["end"] == "2030-01-07T09:40:00Z"
    blocked = await api.post(f"{path}/extend", json={"minutes": 5}, headers=auth(people["alice"]))
    assert blocked.status_code == 409 and "you may extend until then" in blocked.json()["error"]
    theirs = await api.post(f"{path}/release", headers=auth(people["bob"]))
    assert theirs.status_code == 403
    clock.now += 600
    released = await api.post(f"{path}/release", headers=auth(people["alice"]))
    assert released.json()["state"] == "released" and released.json()["end"].endswith("09:10:00Z")
    assert [r.id for r in api.changed] == [mine["id"], mine["id"]]
    assert [r.end - r.start for r in api.changed] == [2400, 600]
    free = await book(api, people["bob"], start=clock.at(10), minutes=30)
    assert free.status_code == 201, free.text


async def test_the_authorizer_answers_the_papers_protocol(api, people, clock):
    """/api/auth answers the seconds left in the key's slot, 0 with a reason for a key
    that opens nothing now (unknown, early, late, another robot's); JSONP with a
    callback; a callback that is not a name is refused."""
    made = (await book(api, people["alice"], start=clock.at(10), minutes=30)).json()
    key = made["key"]["key"]
    early = (await api.get("/api/auth", params={"key": key})).json()
    assert early["seconds"] == 0 and "starts at 2030-01-07 09:10:00 UTC" in early["reason"]
    clock.now += 15 * 60
    assert (await api.get("/api/auth", params={"key": key})).json() == {
        "seconds": 25 * 60,
        "reason": None,
    }
    other = await api.get("/api/auth", params={"key": key, "robot": "pr2-1"})
    assert other.json()["seconds"] == 0 and "for icreate-1, not pr2-1" in other.json()["reason"]
    jsonp = await api.get("/api/auth", params={"key": key, "callback": "lab.authorize"})
    assert jsonp.headers["content-type"].startswith("application/javascript")
    assert jsonp.text == 'lab.authorize({"seconds":1500.0,"reason":null});'
    bad = await api.get("/api/auth", params={"key": key, "callback": "alert(1)//"})
    assert bad.status_code == 422 and "callback must be a JavaScript function name" in bad.text
    forged = await api.get("/api/auth", params={"key": "labd_rk_1_" + "A" * 43})
    assert forged.json()["seconds"] == 0 and "no such key" in forged.json()["reason"]
    for odd in ("labd_rk_1_forged", "labd_rk_1_١٢٣", "labd_rk_²_x", "labd_rk_\uff11_" + "A" * 43):
        answer = await api.get("/api/auth", params={"key": odd})
        assert answer.status_code == 200, (odd, answer.text)
        assert answer.json()["seconds"] == 0
        assert answer.json()["reason"].startswith("this is not a key of this lab"), answer.text
    clock.now += 25 * 60
    late = (await api.get("/api/auth", params={"key": key})).json()
    assert late["seconds"] == 0 and "ended at 2030-01-07 09:40:00 UTC" in late["reason"]


async def test_guessing_keys_is_slowed_down_and_logged(api, clock, caplog):
    """Twenty unknown keys from one address within a minute, and the next answer is a
    429 with Retry-After, unchecked, until the minute has passed; it is logged."""
    for n in range(20):
        reply = await api.get("/api/auth", params={"key": f"labd_rk_1_guess{n}"})
        assert reply.json()["seconds"] == 0
    blocked = await api.get("/api/auth", params={"key": "labd_rk_1_guess"})
    assert blocked.status_code == 429 and blocked.headers["retry-after"] == "60"
    assert "too many failed keys from your address; wait 60 s" in blocked.json()["error"]
    assert any("20 failed key attempts for 203.0.113.5" in r.message for r in caplog.records)
    clock.now += 61
    assert (await api.get("/api/auth", params={"key": "labd_rk_1_x"})).status_code == 200


async def test_my_key_of_the_slot_running_now(api, people, clock):
    """/api/robots/R/key gives my key of R's slot running now, else a 404 saying when
    my next one starts."""
    made = (await book(api, people["alice"], start=clock.at(5), minutes=10)).json()
    none = await api.get("/api/robots/icreate-1/key", headers=auth(people["alice"]))
    assert none.status_code == 404
    assert none.json()["error"] == (
        "alice has no slot of icreate-1 now; your next starts at 2030-01-07 09:05:00 UTC"
        " (/reservations)"
    )
    clock.now += 6 * 60
    now = await api.get("/api/robots/icreate-1/key", headers=auth(people["alice"]))
    assert now.json()["key"] == made["key"]["key"] and now.json()["seconds"] == 9 * 60
    bob = await api.get("/api/robots/icreate-1/key", headers=auth(people["bob"]))
    assert bob.status_code == 404 and "book one" in bob.json()["error"]


async def test_the_calendar_feed_parses_and_shows_who_and_when(api, people, clock):
    """The .ics feed parses with the icalendar library: one event per slot with its
    times in UTC, who booked it, a stable UID, and no key."""
    a = (await book(api, people["alice"], start=clock.at(10), minutes=30)).json()
    b = (await book(api, people["bob"], start=clock.at(60), minutes=15)).json()
    await book(api, people["bob"], "pr2-1", minutes=15)
    feed = await api.get("/api/robots/icreate-1/calendar.ics")
    assert feed.status_code == 200
    assert feed.headers["content-type"] == "text/calendar; charset=utf-8"
    assert a["key"]["key"] not in feed.text and b["key"]["key"] not in feed.text
    cal = Calendar.from_ical(feed.content)
    assert str(cal["version"]) == "2.0" and str(cal["x-wr-calname"]) == "icreate-1 (labd)"
    events = [c for c in cal.walk("VEVENT")]
    assert [str(e["summary"]) for e in events] == ["icreate-1: alice", "icreate-1: bob"]
    assert events[0].decoded("dtstart") == MONDAY + dt.timedelta(minutes=10)
    assert events[0].decoded("dtend") == MONDAY + dt.timedelta(minutes=40)
    assert str(events[0]["uid"]) == f"reservation-{a['reservation']['id']}@lab.test"
    assert (await api.get("/api/robots/r2d2/calendar.ics")).status_code == 404


async def test_tokens_listed_made_and_revoked_by_their_owner(api, people):
    """A user lists their tokens, makes one (shown once), and revokes it: it is refused
    at once with a message saying how to get another."""
    mine = auth(people["alice"])
    made = await api.post("/api/tokens", json={"label": "CI"}, headers=mine)
    assert made.status_code == 201
    new = made.json()["token"]
    assert (await api.get("/api/me", headers=auth(new))).json()["name"] == "alice"
    listed = (await api.get("/api/tokens", headers=mine)).json()["tokens"]
    assert [t["label"] for t in listed] == ["CI", "made by the operator (labd users add)"]
    assert new not in str(listed)
    token_id = made.json()["listed"]["id"]
    stolen = await api.post(f"/api/tokens/{token_id}/revoke", headers=auth(people["bob"]))
    assert stolen.status_code == 404
    await api.post(f"/api/tokens/{token_id}/revoke", headers=mine)
    refused = await api.get("/api/me", headers=auth(new))
    assert refused.status_code == 401 and "unknown or revoked" in refused.json()["error"]


async def test_a_signed_in_page_writes_only_with_its_csrf_token(api, service, people):
    """With the session cookie alone a page may read its user's key, but a write without
    the session's CSRF token is a 403 saying so; with it, the booking goes through."""
    cookie, session = service.accounts.open_session(service.index.user("alice"))
    api.cookies.set("labd_session", cookie)
    assert (await api.get("/api/me")).json()["name"] == "alice"
    refused = await api.post("/api/reservations", json={"robot": "icreate-1", "minutes": 5})
    assert refused.status_code == 403 and "CSRF token in X-CSRF-Token" in refused.json()["error"]
    wrong = await api.post(
        "/api/reservations",
        json={"robot": "icreate-1", "minutes": 5},
        headers={"X-CSRF-Token": "forged"},
    )
    assert wrong.status_code == 403
    made = await api.post(
        "/api/reservations",
        json={"robot": "icreate-1", "minutes": 5},
        headers={"X-CSRF-Token": session.csrf},
    )
    assert made.status_code == 201 and made.json()["reservation"]["user"] == "alice"
    service.accounts.end_session(cookie)
    ended = await api.get("/api/me")
    assert ended.status_code == 401 and "sign in again" in ended.json()["error"]
