"""Accounts and reservations on the pages, in process, with a clock the test moves:
password sign-in and its throttle, self-service sign-up when the operator allows it,
the tokens page, booking, extending and releasing from the pages, and each robot's
public calendar. (tests/integration/test_reservations_browser.py drives them in
Chromium.)"""

from __future__ import annotations

import datetime as dt
import re

import httpx
import pytest
from argon2 import PasswordHasher

from labd.service import Service, ServiceConfig
from labd.web import RobotLink, Site, create_app
from repository.accounts import Accounts
from tests.fakes import WallClock
from tests.labd.test_web import csrf_of

MONDAY = dt.datetime(2030, 1, 7, 9, 0, tzinfo=dt.UTC)
PASSWORD = "correct horse battery"


@pytest.fixture
def clock() -> WallClock:
    return WallClock(MONDAY.timestamp())


def make_service(tmp_path, clock, **options):
    service = Service(ServiceConfig(data=tmp_path / "data", workers=0, **options), clock=clock)
    # cheap argon2 parameters: these tests check the pages, not the hash's cost
    service.accounts = Accounts(service.index, hasher=PasswordHasher(time_cost=1, memory_cost=1024))
    return service


@pytest.fixture
def service(tmp_path, clock):
    service = make_service(tmp_path, clock)
    yield service
    service.index.close()


async def client_of(service, address="198.51.100.7", **site):
    robots = (RobotLink("icreate-1", "icreate-maze", True), RobotLink("pr2-1", "pr2-table", True))
    changed = []
    app = create_app(
        service, Site(robots, **site), on_submit=lambda: None, on_reservation=changed.append
    )
    client = httpx.AsyncClient(
        transport=httpx.ASGITransport(app=app, client=(address, 5000)),
        base_url="http://lab.test",
    )
    client.changed = changed
    return client


@pytest.fixture
async def web(service):
    async with await client_of(service, reservations=True) as client:
        yield client


@pytest.fixture
def alice(service):
    service.index.add_user("alice", token=False)
    service.accounts.set_password("alice", PASSWORD)


async def sign_in(web, name="alice", password=PASSWORD):
    csrf = csrf_of((await web.get("/session")).text)
    return await web.post("/session", data={"name": name, "password": password, "csrf": csrf})


async def test_password_sign_in_and_out(web, alice):
    """The right password signs in (a session cookie, HttpOnly and SameSite); a wrong one
    is refused saying so; signing out ends the session on the server too."""
    wrong = await sign_in(web, password="not the password")
    assert wrong.status_code == 401 and "the user name or the password is wrong" in wrong.text
    assert 'value="alice"' in wrong.text  # the name is kept on the form
    signed = await sign_in(web)
    assert signed.status_code == 303
    cookie = signed.headers["set-cookie"]
    assert "labd_session=" in cookie and "httponly" in cookie.lower()
    home = await web.get("/")
    assert 'id="me">alice</a>' in home.text
    ended = await web.post("/session/end", data={"csrf": csrf_of(home.text)})
    assert ended.status_code == 303
    assert 'id="me"' not in (await web.get("/")).text


async def test_guessing_passwords_is_refused_for_a_while_and_logged(
    web, service, alice, clock, caplog
):
    """Five wrong passwords for a name from one address and the sixth attempt from
    there, right or not, is refused unchecked for five minutes; it is logged; the owner
    at another address signs in meanwhile; after that the right one works."""
    for _ in range(5):
        assert (await sign_in(web, password="guess guess guess")).status_code == 401
    blocked = await sign_in(web)
    assert blocked.status_code == 429 and blocked.headers["retry-after"] == "300"
    assert (
        "too many failed sign-ins for alice from your address; wait 300 s and try again"
        in blocked.text
    )
    logged = "5 failed password attempts for 'alice' from 198.51.100.7"
    assert any(logged in r.message for r in caplog.records)
    async with await client_of(service, address="203.0.113.9") as owner:
        assert (await sign_in(owner)).status_code == 303
    clock.now += 301
    assert (await sign_in(web)).status_code == 303


async def test_sign_up_only_where_the_operator_allows_it(tmp_path, clock):
    """Sign-up is a page saying who makes accounts, unless the lab runs with --signup;
    then a person signs up and is signed in at once, and bad input says what to fix."""
    closed = make_service(tmp_path / "closed", clock)
    async with await client_of(closed) as web:
        page = await web.get("/signup")
        assert page.status_code == 404 and "Sign-up is closed here" in page.text
    closed.index.close()
    service = make_service(tmp_path / "open", clock, signup=True)
    async with await client_of(service) as web:
        csrf = csrf_of((await web.get("/signup")).text)
        form = {"name": "carol", "password": PASSWORD, "again": PASSWORD, "csrf": csrf}
        differ = await web.post("/signup", data={**form, "again": "something else"})
        assert differ.status_code == 422 and "the two passwords differ" in differ.text
        short = await web.post("/signup", data={**form, "password": "short", "again": "short"})
        assert "at least 10 characters" in short.text
        bad = await web.post("/signup", data={**form, "name": "no spaces"})
        assert "use 1 to 64 ASCII letters" in bad.text
        made = await web.post("/signup", data=form)
        assert made.status_code == 303 and made.headers["location"] == "/reservations"
        assert 'id="me">carol</a>' in (await web.get("/reservations")).text
        taken = await web.post("/signup", data={**form, "csrf": csrf_of((await web.get("/")).text)})
        assert "exists already" in taken.text
    service.index.close()


async def test_the_tokens_page(web, service, alice):
    """A signed-in person makes a token (shown once, and it works), sees it listed by
    label, and revokes it."""
    await sign_in(web)
    page = await web.get("/tokens")
    made = await web.post("/tokens", data={"label": "laptop", "csrf": csrf_of(page.text)})
    assert made.status_code == 201 and made.headers["cache-control"] == "no-store"
    token = re.search(r'<pre id="token">([^<]+)</pre>', made.text).group(1)
    assert service.index.user_by_token(token).name == "alice"
    listed = await web.get("/tokens")
    assert "laptop" in listed.text and token not in listed.text
    [listing] = service.accounts.tokens("alice")
    revoked = await web.post(f"/tokens/{listing.id}/revoke", data={"csrf": csrf_of(listed.text)})
    assert revoked.status_code == 303
    assert service.index.user_by_token(token) is None


async def test_booking_extending_and_releasing_from_the_pages(web, service, alice, clock):
    """A person books from the form, sees the slot on the robot's card and in their
    slots, extends it by 15 minutes and ends it; a refused booking is shown on the form
    with what was typed kept."""
    anonymous = await web.get("/reservations")
    assert "sign in</a> first" in anonymous.text
    await sign_in(web)
    csrf = csrf_of((await web.get("/reservations")).text)
    made = await web.post(
        "/reservations",
        data={"robot": "icreate-1", "start": "2030-01-07T10:00", "minutes": "30", "csrf": csrf},
    )
    assert made.status_code == 303, made.text
    page = await web.get(made.headers["location"])
    assert "Done: booked" in page.text
    card = page.text[page.text.index('id="robot-icreate-1"') :]
    assert "2030-01-07 10:00:00 UTC</dt><dd>30 min · alice" in card
    [slot] = service.reservations.find(user="alice")
    too_long = await web.post(
        "/reservations",
        data={"robot": "pr2-1", "start": "2030-01-07 12:00", "minutes": "600", "csrf": csrf},
    )
    assert too_long.status_code == 422 and "at most 60 min here" in too_long.text
    assert 'value="600"' in too_long.text and 'value="2030-01-07 12:00"' in too_long.text
    past = await web.post(
        "/reservations",
        data={"robot": "pr2-1", "start": "2030-01-06 12:00", "minutes": "10", "csrf": csrf},
    )
    assert "in the past" in past.text
    longer = await web.post(f"/reservations/{slot.id}/extend", data={"csrf": csrf, "minutes": "15"})
    assert longer.status_code == 303
    assert service.reservations.get(slot.id).end == slot.end + 900
    clock.now = slot.start + 60
    ended = await web.post(f"/reservations/{slot.id}/release", data={"csrf": csrf})
    assert ended.status_code == 303
    assert service.reservations.get(slot.id).end == slot.start + 60
    assert [r.id for r in web.changed] == [slot.id, slot.id]


async def test_the_calendar_page_is_public_and_links_its_feed(web, service, clock):
    """Anyone sees who booked a robot and when, day by day, with the feed to subscribe
    to; never a key; an unknown robot is a page saying which can be booked."""
    service.index.add_user("bob")
    made = service.reservations.book("bob", "icreate-1", clock.now + 3600, clock.now + 5400)
    page = await web.get("/reservations/icreate-1")
    assert page.status_code == 200
    assert (
        "Monday 2030-01-07" in page.text and "<td>10:00</td><td>10:30</td><td>bob</td>" in page.text
    )
    assert 'href="http://lab.test/api/robots/icreate-1/calendar.ics"' in page.text
    assert 'href="webcal://lab.test/api/robots/icreate-1/calendar.ics"' in page.text
    assert made.key not in page.text
    missing = await web.get("/reservations/r2d2")
    assert missing.status_code == 404 and "icreate-1, pr2-1" in missing.text


async def test_changing_my_password(web, service, alice):
    """A signed-in person changes their password on /password: a wrong current password
    or two new ones that differ are refused saying so; the change signs out their other
    session and keeps this one."""
    other, _ = service.accounts.open_session(service.index.user("alice"))
    assert (await web.get("/password")).status_code == 303  # sign in first
    assert (await sign_in(web)).status_code == 303
    csrf = csrf_of((await web.get("/password")).text)
    form = {"current": PASSWORD, "password": "a new long password", "again": "a new long password"}
    wrong = await web.post("/password", data={**form, "current": "not it at all", "csrf": csrf})
    assert wrong.status_code == 401 and "that is not your current password" in wrong.text
    differ = await web.post("/password", data={**form, "again": "something else", "csrf": csrf})
    assert differ.status_code == 422 and "the two new passwords differ" in differ.text
    assert service.accounts.session(other) is not None
    done = await web.post("/password", data={**form, "csrf": csrf})
    assert done.status_code == 303 and done.headers["location"] == "/password?done=1"
    shown = await web.get(done.headers["location"])
    assert "Your password is changed; your other sign-ins (1) have ended." in shown.text
    assert service.accounts.session(other) is None
    assert service.accounts.check_password("alice", "a new long password").name == "alice"


async def test_the_pages_refuse_as_the_api_does(web, service, alice, clock):
    """A booking that clashes, someone else's slot, a slot that does not exist: each is
    shown on the booking page with the status the API answers the same error with (409,
    403, 404), what was typed kept; signed out, a form sends the person to sign in and
    back to the page it is on."""
    service.index.add_user("bob")
    theirs = service.reservations.book("bob", "icreate-1", clock.now + 3600, clock.now + 5400)
    await sign_in(web)
    csrf = csrf_of((await web.get("/reservations")).text)
    form = {"robot": "icreate-1", "start": "2030-01-07 10:15", "minutes": "30", "csrf": csrf}
    clash = await web.post("/reservations", data=form)
    assert clash.status_code == 409 and "is booked from" in clash.text and "by bob" in clash.text
    assert 'value="2030-01-07 10:15"' in clash.text
    api = await web.post(
        "/api/reservations",
        json={"robot": "icreate-1", "start": "2030-01-07T10:15:00Z", "minutes": 30},
        headers={"X-CSRF-Token": csrf},
    )
    assert api.status_code == 409 and api.json()["error"] in clash.text
    reservation = theirs.reservation.id
    other = await web.post(f"/reservations/{reservation}/release", data={"csrf": csrf})
    assert other.status_code == 403 and "only they may" in other.text
    none = await web.post("/reservations/999/extend", data={"csrf": csrf, "minutes": "15"})
    assert none.status_code == 404 and "no reservation &#39;999&#39;" in none.text
    nobody = await client_of(service)
    async with nobody:
        visitor = csrf_of((await nobody.get("/reservations")).text)
        sent = await nobody.post(f"/reservations/{reservation}/extend", data={"csrf": visitor})
        assert sent.status_code == 303
        assert sent.headers["location"] == "/session?then=/reservations"
        tokens = await nobody.get("/tokens")
        assert tokens.status_code == 303 and tokens.headers["location"] == "/session?then=/tokens"
