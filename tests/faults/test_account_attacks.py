"""Attacks on accounts, keys and bookings (issue 24), against a real ``labd serve``.

Each test runs the lab as its own process with reservations and sign-up on, and
attacks it the way the issue's attacker did: HTTP from several loopback addresses
(127.0.0.1, 127.0.0.2, ...: every 127/8 address reaches the lab, each is another
client address), the pages' own forms with their CSRF tokens, real WebSocket clients
on the bridge, and the operator's ``labd users`` command in a process of its own.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import re
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import httpx
import pytest
import websockets
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect as connect_ws

from labd.service import ServiceConfig
from tests.faults.conftest import Served, wait_for
from tests.helpers.timing import SECOND

pytestmark = [pytest.mark.integration, pytest.mark.rates, pytest.mark.timeout(180)]
PASSWORD = "correct horse battery"
RECHECK = 1.0  # seconds between the bridge's re-checks of connected keys (--key-recheck)
ARGS = (
    "--reservations",
    "--signup",
    "--workers", "0",
    "--robot", "icreate-1=icreate-maze",
    "--no-playground",
    "--key-recheck", str(RECHECK),
)  # fmt: skip


@pytest.fixture
def served_lab(served: Any) -> Served:
    """A lab with reservations and sign-up, one live robot, and alice (password, token)."""
    served_lab: Served = served(*ARGS).start()
    served_lab.token = add_user(served_lab, "alice", PASSWORD)
    return served_lab


def add_user(served_lab: Served, name: str, password: str) -> str:
    """``labd users add NAME --password-stdin``, as the operator types it; the token."""
    done = operator(served_lab, "add", name, "--password-stdin", "--json", stdin=password + "\n")
    return str(json.loads(done.stdout)["token"])


def operator(served_lab: Served, *args: str, stdin: str = "") -> subprocess.CompletedProcess[str]:
    """A ``labd users`` command on the lab's data folder, in a process of its own."""
    done = subprocess.run(
        [sys.executable, "-m", "labd", "users", *args, "--data", str(served_lab.data)],
        input=stdin,
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    return done


@pytest.fixture
def browsers(served_lab: Served) -> Iterator[Any]:
    """Browsers of the lab from a given loopback address: ``browsers("127.0.0.2")``."""
    made: list[httpx.Client] = []

    def make(address: str = "127.0.0.1") -> httpx.Client:
        client = httpx.Client(
            base_url=served_lab.server,
            transport=httpx.HTTPTransport(local_address=address),
            timeout=30,
        )
        made.append(client)
        return client

    yield make
    for client in made:
        client.close()


def csrf(browser: httpx.Client, path: str) -> str:
    """The CSRF token of a page (its ``<meta name="csrf-token">``)."""
    found = re.search(r'<meta name="csrf-token" content="([^"]+)">', browser.get(path).text)
    assert found is not None, path
    return found.group(1)


def sign_in(browser: httpx.Client, name: str, password: str, **headers: str) -> httpx.Response:
    fields = {"name": name, "password": password, "csrf": csrf(browser, "/session")}
    return browser.post("/session", data=fields, headers=headers)


def sign_up(browser: httpx.Client, name: str, **headers: str) -> httpx.Response:
    fields = {
        "name": name,
        "password": PASSWORD,
        "again": PASSWORD,
        "csrf": csrf(browser, "/signup"),
    }
    return browser.post("/signup", data=fields, headers=headers)


def problem(page: httpx.Response) -> str:
    """The sentence a refused form shows (its ``#problem``)."""
    found = re.search(r'<p class="notice" id="problem">([^<]*)</p>', page.text)
    assert found is not None, page.text[:2000]
    return found.group(1).replace("&#39;", "'").replace("&#34;", '"')


def bearer(token: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {token}"}


def book(served_lab: Served, token: str, **body: Any) -> httpx.Response:
    return httpx.post(
        f"{served_lab.server}/api/reservations",
        json={"robot": "icreate-1", **body},
        headers=bearer(token),
        timeout=30,
    )


def robot(served_lab: Served) -> str:
    return f"{served_lab.bridge}/robots/icreate-1"


def closed_reason(ws: Any, timeout: float) -> tuple[int, str]:
    """The close code and reason the lab sends, waiting at most ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    with pytest.raises(ConnectionClosed) as info:
        while True:
            ws.recv(timeout=max(0.01, deadline - time.monotonic()))
    assert info.value.rcvd is not None, "the lab did not close the connection"
    return info.value.rcvd.code, info.value.rcvd.reason


def authorized(ws: Any, key: str) -> None:
    """Present ``key`` and wait until the lab answers a call made after it."""
    ws.send(json.dumps({"op": "auth", "key": key}))
    ws.send(json.dumps({"op": "call_service", "id": "after", "service": "/rosapi/nodes"}))
    while json.loads(ws.recv(timeout=10)).get("id") != "after":
        pass


# -- 1. keys of a revoked user ------------------------------------------------------------


def test_a_revoked_users_keys_stop_opening_the_robot(served_lab: Served) -> None:
    """Once the operator revokes alice (`labd users revoke alice`), her slot's key opens
    nothing (/api/auth answers 0 seconds, the bridge refuses it) and her connected
    client is disconnected within the bridge's re-check of keys, told why."""
    made = book(served_lab, served_lab.token, minutes=30)
    assert made.status_code == 201, made.text
    key = made.json()["key"]["key"]
    with connect_ws(robot(served_lab)) as ws:
        authorized(ws, key)
        operator(served_lab, "revoke", "alice")
        revoked = time.monotonic()
        answer = httpx.get(f"{served_lab.server}/api/auth", params={"key": key}, timeout=30).json()
        assert answer["seconds"] == 0, answer
        code, reason = closed_reason(ws, timeout=RECHECK + 10)
        # the revocation was written when the command ended, at the latest
        print(f"\nrevoked key's client disconnected {time.monotonic() - revoked:.2f} s after")
    assert code == 1008 and reason.startswith("your key no longer opens icreate-1:"), reason
    with connect_ws(robot(served_lab) + f"?key={key}") as again:
        code, reason = closed_reason(again, timeout=10)
    assert code == 1008 and reason.startswith("authorization refused: the lab knows no such key")


# -- 2. keys with Unicode digits ----------------------------------------------------------

ODD_KEYS = [
    "labd_rk_1_١٢٣",  # Arabic-Indic digits where the MAC goes
    "labd_rk_²_abc",  # a superscript two: a "digit" that int() refuses
    "labd_rk_\uff11_" + "A" * 43,  # a fullwidth one as the reservation's number
    "labd_rk_\u0661_" + "A" * 43,  # an Arabic-Indic one likewise
    "labd_rk_1_" + "A" * 42 + "é",  # one letter outside ASCII
]


def test_keys_with_unicode_digits_are_refused_at_once(served_lab: Served) -> None:
    """A key with a Unicode digit or letter is no key: /api/auth answers 0 seconds with
    the reason (never a 500), and the bridge closes such a client at once, saying why."""
    assert book(served_lab, served_lab.token, minutes=30).status_code == 201  # reservation 1 exists
    for key in ODD_KEYS:
        answer = httpx.get(f"{served_lab.server}/api/auth", params={"key": key}, timeout=30)
        assert answer.status_code == 200, (key, answer.status_code, answer.text)
        assert answer.json()["seconds"] == 0, (key, answer.text)
        assert answer.json()["reason"].startswith("this is not a key of this lab"), answer.text
    for key in ODD_KEYS[:2]:
        started = time.monotonic()
        with connect_ws(robot(served_lab)) as ws:
            ws.send(json.dumps({"op": "auth", "key": key}))
            code, reason = closed_reason(ws, timeout=5)
        assert time.monotonic() - started < 5
        assert code == 1008, (key, code, reason)
        assert reason.startswith("authorization refused: this is not a key of this lab"), reason


# -- 3. 200 clients authorizing at once ---------------------------------------------------


class Silent:
    """A TCP server that accepts connections and never answers (a git server that hung):
    ``accepted`` counts them; ``close`` drops them all."""

    def __init__(self) -> None:
        self.socket = socket.create_server(("127.0.0.1", 0))
        self.port = int(self.socket.getsockname()[1])
        self.held: list[socket.socket] = []
        self._thread = threading.Thread(target=self._accept, daemon=True)
        self._thread.start()

    @property
    def accepted(self) -> int:
        return len(self.held)

    def _accept(self) -> None:
        with contextlib.suppress(OSError):
            while True:
                self.held.append(self.socket.accept()[0])

    def close(self) -> None:
        with contextlib.suppress(OSError):  # wakes the accepting thread
            self.socket.shutdown(socket.SHUT_RDWR)
        self._thread.join(10)
        self.socket.close()
        for held in self.held:
            held.close()


def p99(seconds: list[float]) -> float:
    ordered = sorted(seconds)
    return ordered[max(0, int(len(ordered) * 0.99) - 1)]


async def authorize_200(served_lab: Served, key: str) -> tuple[list[float], list[float]]:
    """200 /api/auth requests at once, then 200 bridge clients presenting the key at
    once, each from a loopback address of its own, each authorized; the seconds each took."""
    addresses = [f"127.0.1.{n}" for n in range(1, 201)]
    clients = [
        httpx.AsyncClient(
            base_url=served_lab.server,
            transport=httpx.AsyncHTTPTransport(local_address=address),
            timeout=60 * SECOND,
        )
        for address in addresses
    ]

    async def ask(client: httpx.AsyncClient) -> float:
        started = time.perf_counter()
        answer = await client.get("/api/auth", params={"key": key, "robot": "icreate-1"})
        assert answer.status_code == 200 and answer.json()["seconds"] > 0, answer.text
        return time.perf_counter() - started

    async def connect(address: str) -> float:
        started = time.perf_counter()
        async with websockets.connect(
            robot(served_lab), local_addr=(address, 0), open_timeout=60 * SECOND, compression=None
        ) as ws:
            await ws.send(json.dumps({"op": "auth", "key": key}))
            await ws.send(json.dumps({"op": "call_service", "id": "a", "service": "/rosapi/nodes"}))
            while json.loads(await asyncio.wait_for(ws.recv(), 60 * SECOND)).get("id") != "a":
                pass
            return time.perf_counter() - started

    try:
        http = await asyncio.gather(*(ask(c) for c in clients))
    finally:
        await asyncio.gather(*(c.aclose() for c in clients))
    bridge = await asyncio.gather(*(connect(a) for a in addresses))
    return list(http), list(bridge)


def test_200_clients_authorize_at_once_while_every_submission_thread_is_held(
    served: Any,
) -> None:
    """While 40 submissions wait on a git server that never answers, for as long as the
    test holds them (every thread of the submissions' pool held, the rest waiting their
    turn), 200 clients asking /api/auth at once and 200 bridge clients presenting a key
    at once are each authorized: the authorizer waits for no thread of theirs."""
    # the silent git server is on loopback, which submissions reach only when allowed; it
    # holds them until it closes: no time limit of the lab's ends them first
    lab = served(
        *ARGS, "--fetch-timeout", "3600", "--resolve-timeout", "3600", "--allow-private-hosts"
    ).start()
    lab.token = add_user(lab, "alice", PASSWORD)
    made = book(lab, lab.token, minutes=30)
    assert made.status_code == 201, made.text
    key = made.json()["key"]["key"]
    silent = Silent()
    pool = ThreadPoolExecutor(40)
    try:
        held = [
            pool.submit(
                httpx.post,
                f"{lab.server}/api/trials",
                json={"repository": f"git://127.0.0.1:{silent.port}/r{n}.git"},
                headers=bearer(lab.token),
                timeout=None,  # held until the silent server closes
            )
            for n in range(40)
        ]
        threads = ServiceConfig().submit_threads
        wait_for(
            f"{threads} submissions to reach the silent git server",
            lambda: silent.accepted >= threads,
            60 * SECOND,
        )
        http, bridge = asyncio.run(authorize_200(lab, key))
        print(  # how fast: bench/crowds.py measures it against the same without the held pool
            f"\n/api/auth, 200 at once: p50 {sorted(http)[100]:.3f} s, p99 {p99(http):.3f} s;"
            f" bridge, 200 at once: p50 {sorted(bridge)[100]:.3f} s, p99 {p99(bridge):.3f} s"
        )
        assert len(http) == len(bridge) == 200  # each authorized (checked as it came)
        assert not any(h.done() for h in held)  # the submissions were held throughout
        assert silent.accepted >= threads  # their threads too
    finally:
        silent.close()
        pool.shutdown(wait=True)


# -- 4. a password change ends the other sessions -----------------------------------------


def test_a_password_change_or_reset_ends_the_other_sessions(
    served_lab: Served, browsers: Any
) -> None:
    """Alice changes her password on the page: her other signed-in browser is signed
    out, this one stays; the operator's reset (`labd users password`) ends every
    session; her API token survives both (as documented)."""
    here, there = browsers(), browsers("127.0.0.2")
    for browser in (here, there):
        assert sign_in(browser, "alice", PASSWORD).status_code == 303
        assert browser.get("/api/me").status_code == 200
    new = "another long password"
    fields = {"current": PASSWORD, "password": new, "again": new, "csrf": csrf(here, "/password")}
    changed = here.post("/password", data=fields)
    assert changed.status_code == 303, changed.text[:2000]
    assert there.get("/api/me").status_code == 401
    assert here.get("/api/me").status_code == 200
    assert sign_in(there, "alice", PASSWORD).status_code == 401  # the old one is refused
    assert sign_in(there, "alice", new).status_code == 303
    operator(served_lab, "password", "alice", "--password-stdin", stdin="a third long password\n")
    assert here.get("/api/me").status_code == 401
    assert there.get("/api/me").status_code == 401
    me = httpx.get(f"{served_lab.server}/api/me", headers=bearer(served_lab.token), timeout=30)
    assert me.status_code == 200 and me.json()["name"] == "alice"


# -- 5. and 6. the sign-in throttles ------------------------------------------------------


def test_wrong_passwords_from_another_address_do_not_lock_the_owner_out(
    served_lab: Served, browsers: Any
) -> None:
    """An attacker at 127.0.0.2 is refused (429) after five wrong passwords for alice,
    while alice, at 127.0.0.1, still signs in with hers."""
    attacker, owner = browsers("127.0.0.2"), browsers("127.0.0.1")
    for _ in range(5):
        assert sign_in(attacker, "alice", "a wrong password").status_code == 401
    refused = sign_in(attacker, "alice", PASSWORD)
    assert refused.status_code == 429, refused.status_code
    assert problem(refused).startswith("too many failed sign-ins for alice from your address")
    assert sign_in(owner, "alice", PASSWORD).status_code == 303


def test_a_forged_forwarded_for_does_not_change_the_address_throttled(
    served_lab: Served, browsers: Any
) -> None:
    """With no --trusted-proxy, X-Forwarded-For is ignored: 20 failed sign-ins (each
    claiming another address) and 20 unknown keys (likewise) from 127.0.0.1 are throttled
    as that one address."""
    attacker = browsers("127.0.0.1")
    for n in range(20):
        forged = {"X-Forwarded-For": f"198.51.100.{n}"}
        assert sign_in(attacker, f"guess{n}", "a wrong password", **forged).status_code == 401
    refused = sign_in(attacker, "guess20", "a wrong password", **{"X-Forwarded-For": "192.0.2.7"})
    assert refused.status_code == 429, refused.status_code
    assert problem(refused).startswith("too many failed sign-ins from your address")
    codes = [
        attacker.get(
            "/api/auth",
            params={"key": f"labd_rk_{n + 1}_" + "A" * 43},
            headers={"X-Forwarded-For": f"198.51.100.{n}"},
        ).status_code
        for n in range(21)
    ]
    assert codes == [200] * 20 + [429], codes


# -- 7. sign-up ---------------------------------------------------------------------------


LOOK_ALIKES = [
    ("\u0430lice", "user name '\u0430lice': use 1 to 64 ASCII letters"),  # a Cyrillic a
    ("Alice", "user name 'Alice' is taken: names are told apart without case"),
    ("..", "user name '..': use 1 to 64 ASCII letters"),
    (".", "user name '.': use 1 to 64 ASCII letters"),
    ("\uff41lice", "user name '\uff41lice': use 1 to 64 ASCII letters"),  # a fullwidth a
]


def test_look_alike_names_are_refused_at_sign_up(served_lab: Served, browsers: Any) -> None:
    """A name that looks like alice's (another script, other capitals, fullwidth), or
    is only dots, is refused on the sign-up page (422, naming the rule), and no account
    is made."""
    for name, expected in LOOK_ALIKES:
        answer = sign_up(browsers(), name)
        assert answer.status_code == 422, (name, answer.status_code)
        assert problem(answer).startswith(expected), problem(answer)
    listed = json.loads(operator(served_lab, "list", "--json").stdout)
    assert [row["name"] for row in listed] == ["alice"]


def test_sign_ups_are_throttled_per_address(served_lab: Served, browsers: Any) -> None:
    """One address makes at most 5 accounts an hour; the 6th is refused (429) saying
    when to try again; another address may still sign up."""
    browser = browsers("127.0.0.3")
    for n in range(5):
        assert sign_up(browser, f"bot{n}").status_code == 303
        browser.cookies.clear()  # each sign-up signs in: start afresh, as a script would
    refused = sign_up(browser, "bot5")
    assert refused.status_code == 429, refused.status_code
    assert problem(refused).startswith("too many sign-ups from your address; wait")
    assert sign_up(browsers("127.0.0.4"), "carol").status_code == 303


# -- 8. far-future and far-past booking times ---------------------------------------------

FAR = [
    {"minutes": -1e300},
    {"minutes": 1e300},
    {"start": "9999-12-31T23:59:00Z", "minutes": 30},
    {"start": "9999-12-31T23:00:00Z", "end": "9999-12-31T23:59:59Z"},
    {"start": "0001-01-01T00:00:00Z", "minutes": 30},
    {"minutes": 1e12 / 60},  # a slot of 10^12 seconds
]


def test_far_future_bookings_are_refused_with_a_4xx(served_lab: Served, browsers: Any) -> None:
    """Booking times out of any calendar (year 9999, 10^12 s, -10^300 minutes) are
    refused with a 4xx naming the rule, through the API and the booking form; a lab
    cannot be told to book further ahead than a year."""
    for body in FAR:
        answer = book(served_lab, served_lab.token, **body)
        assert 400 <= answer.status_code < 500, (body, answer.status_code, answer.text)
        assert answer.json()["error"], answer.text
    browser = browsers()
    assert sign_in(browser, "alice", PASSWORD).status_code == 303
    for minutes in ("-1e300", "1e300", "1e12"):
        form = {"robot": "icreate-1", "start": "", "minutes": minutes}
        answer = browser.post("/reservations", data={**form, "csrf": csrf(browser, "/")})
        assert answer.status_code == 422, (minutes, answer.status_code)
    other = served_lab.data.parent / "other"
    command = ["serve", "--data", str(other), "--http-port", "0", "--bridge-port", "0"]
    refused = subprocess.run(
        [sys.executable, "-m", "labd", *command, "--book-ahead", "1e6"],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert refused.returncode != 0
    assert "--book-ahead may be at most 365 days" in refused.stderr, refused.stderr
