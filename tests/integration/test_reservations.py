"""The bridge behind the lab's own authorizer, for real (``labd serve --reservations``):
a slot's key drives its robot and the drive is filed under its owner; a watcher without
a key, an expired key, a key not yet valid and another robot's key are refused saying
why; the connection is warned before its slot ends and closed when it does; a slot
released through the API disconnects its client at once."""

from __future__ import annotations

import json
import time

import httpx
import pytest
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect as connect_ws

from labd.bridge.auth import AuthError, AuthUnavailable, Grant
from labd.config import BridgeConfig
from repository.index import Filters
from repository.trial import Kind
from tests.helpers.labs import MAZE, PR2, ServerThread, lab_config, running

pytestmark = [pytest.mark.integration, pytest.mark.timeout(120)]
TWIST = "geometry_msgs/msg/Twist"
WAIT = 10


@pytest.fixture
def server(tmp_path):
    """A lab whose live robots (icreate-1, pr2-1) are driven only in a reserved slot,
    warned 2 s before the slot ends."""
    bridge = BridgeConfig(port=0, expiry_warning=2.0)
    config = lab_config(tmp_path / "data", (MAZE, PR2), bridge=bridge, reservations=True)
    with running(config) as server:
        yield server


def robot_url(server: ServerThread, robot: str = "icreate-1") -> str:
    return server.url + f"/robots/{robot}"


def book(
    server: ServerThread,
    user: str,
    seconds: float,
    *,
    start: float | None = None,
    robot="icreate-1",
):
    desk = server.lab.service.reservations
    begin = time.time() if start is None else start
    return desk.book(user, robot, begin, begin + seconds)


def frames_until(ws, predicate):
    """Frames received until one satisfies ``predicate`` (which is returned last)."""
    seen = []
    deadline = time.monotonic() + WAIT
    while time.monotonic() < deadline:
        frame = json.loads(ws.recv(timeout=WAIT))
        seen.append(frame)
        if predicate(frame):
            return seen
    raise AssertionError(f"no such frame in {seen}")


def closed_reason(ws) -> tuple[int, str]:
    with pytest.raises(ConnectionClosed) as info:
        while True:
            ws.recv(timeout=WAIT)
    assert info.value.rcvd is not None
    return info.value.rcvd.code, info.value.rcvd.reason


def drive(ws, x=0.2):
    ws.send(json.dumps({"op": "publish", "topic": "/cmd_vel", "msg": {"linear": {"x": x}}}))


def test_a_key_drives_is_warned_and_closed_when_its_slot_ends(server):
    """Alice's key drives icreate-1 (the robot says she drives); a minute-like warning
    (2 s here) comes before her 4 s slot ends, then the connection closes, and her drive
    is filed as a demonstration under her name."""
    for name in ("alice", "bob"):
        server.lab.service.index.add_user(name)
    made = book(server, "alice", 4.0)
    drives = server.lab.drives["icreate-1"]
    with connect_ws(robot_url(server)) as ws:
        ws.send(json.dumps({"op": "auth", "key": made.key}))
        ws.send(json.dumps({"op": "set_level", "level": "warning"}))
        ws.send(json.dumps({"op": "advertise", "topic": "/cmd_vel", "type": TWIST}))
        drive(ws)
        server.wait_until(lambda: drives.current is not None)
        assert drives.current.user == "alice"
        seen = frames_until(ws, lambda f: f.get("op") == "status")
        assert seen[-1]["level"] == "warning"
        assert seen[-1]["msg"].startswith("the time of your key ends in 2 s")
        code, reason = closed_reason(ws)
    assert (code, reason) == (1008, "the authorization has expired")
    service = server.lab.service
    deadline = time.monotonic() + 30
    while not (found := service.index.find(Filters(kind=Kind.DEMONSTRATION)).items):
        assert time.monotonic() < deadline, "no demonstration filed"
        time.sleep(0.1)
    assert [d.submitter for d in found] == ["alice"]


def test_without_a_key_a_client_watches_and_cannot_drive(server):
    """A client without a key connects and sees the robot, but its commands are refused
    with how to book."""
    with connect_ws(robot_url(server)) as ws:
        ws.send(json.dumps({"op": "set_level", "level": "error"}))
        ws.send(json.dumps({"op": "subscribe", "topic": "/odom", "type": "nav_msgs/msg/Odometry"}))
        frames_until(ws, lambda f: f.get("topic") == "/odom")
        ws.send(json.dumps({"op": "advertise", "topic": "/cmd_vel", "type": TWIST}))
        drive(ws)
        seen = frames_until(ws, lambda f: f.get("op") == "status")
    assert "icreate-1 is driven only in a reserved slot; you are watching" in seen[-1]["msg"]
    assert server.lab.drives["icreate-1"].current is None


@pytest.mark.parametrize("case", ["expired", "early", "other robot", "forged"])
def test_keys_that_open_nothing_now_are_refused_saying_why(server, case):
    """An expired key, a key of a later slot, another robot's key and a forged key each
    close the connection with a reason its holder can act on."""
    server.lab.service.index.add_user("bob")
    now = time.time()
    if case == "expired":
        made = book(server, "bob", 0.2)
        while time.time() <= made.reservation.end:  # until the slot has ended
            time.sleep(0.01)
        expected = "this key's slot on icreate-1 ended at"
    elif case == "early":
        made = book(server, "bob", 60, start=now + 600)
        expected = "this key's slot on icreate-1 starts at"
    elif case == "other robot":
        made = book(server, "bob", 60, robot="pr2-1")
        expected = "this key is for pr2-1, not icreate-1"
    else:
        made = book(server, "bob", 60)
        made = type(made)(made.reservation, made.key[:-3] + "xyz")
        expected = "the lab knows no such key"
    with connect_ws(robot_url(server) + f"?key={made.key}") as ws:
        code, reason = closed_reason(ws)
    assert code == 1008 and reason.startswith(f"authorization refused: {expected}")


def test_a_slot_released_through_the_api_disconnects_its_client(server):
    """Alice releases her slot through the API while connected with its key: she is
    disconnected at once, told why, and Bob can book the rest."""
    service = server.lab.service
    token = service.index.add_user("alice")
    bob = service.index.add_user("bob")
    http = server.lab.http.url()
    with httpx.Client(base_url=http, headers={"Authorization": f"Bearer {token}"}) as api:
        made = api.post("/api/reservations", json={"robot": "icreate-1", "minutes": 30})
        assert made.status_code == 201, made.text
        key = made.json()["key"]["key"]
        slot = made.json()["reservation"]["id"]
        with connect_ws(robot_url(server)) as ws:
            ws.send(json.dumps({"op": "auth", "key": key}))
            ws.send(json.dumps({"op": "call_service", "id": 1, "service": "/rosapi/nodes"}))
            frames_until(ws, lambda f: f.get("id") == 1)
            assert api.post(f"/api/reservations/{slot}/release").status_code == 200
            code, reason = closed_reason(ws)
    assert (code, reason) == (1008, "your slot on icreate-1 was released")
    taken = httpx.post(
        f"{http}/api/reservations",
        json={"robot": "icreate-1", "minutes": 20},
        headers={"Authorization": f"Bearer {bob}"},
    )
    assert taken.status_code == 201, taken.text


def test_two_people_each_drive_only_in_their_own_slot(server):
    """Alice and Bob book back-to-back slots: during Alice's, Bob's key is refused and
    Alice drives; when hers ends, Bob's key opens the robot and he drives."""
    for name in ("alice", "bob"):
        server.lab.service.index.add_user(name)
    start = time.time()
    alice = book(server, "alice", 3.0, start=start)
    bob = book(server, "bob", 30.0, start=start + 3.0)
    drives = server.lab.drives["icreate-1"]
    with connect_ws(robot_url(server) + f"?key={bob.key}") as early:
        assert "starts at" in closed_reason(early)[1]
    with connect_ws(robot_url(server) + f"?key={alice.key}") as ws:
        ws.send(json.dumps({"op": "advertise", "topic": "/cmd_vel", "type": TWIST}))
        drive(ws)
        server.wait_until(lambda: drives.current is not None and drives.current.user == "alice")
        assert closed_reason(ws) == (1008, "the authorization has expired")
    server.wait_until(lambda: drives.current is None)
    with connect_ws(robot_url(server) + f"?key={bob.key}") as ws:
        ws.send(json.dumps({"op": "advertise", "topic": "/cmd_vel", "type": TWIST}))
        drive(ws)
        server.wait_until(lambda: drives.current is not None and drives.current.user == "bob")


class Refusing:
    """An authorizer that refuses every key, and counts the keys it was asked about."""

    def __init__(self) -> None:
        self.asked: list[str] = []

    async def authorize(self, key: str, graph: str) -> Grant:
        self.asked.append(key)
        raise AuthError("the lab knows no such key")


def test_guessing_keys_on_the_bridge_is_cut_short(make_server, caplog):
    """After the allowed number of refused keys from one address, the next key is refused
    without asking the authorizer, saying when to try again; it is logged."""
    refusing = Refusing()
    server = make_server(
        BridgeConfig(port=0, auth_failures=3, auth_failure_window=60), authorizer=refusing
    )
    for key in ("a", "b", "c", "d"):
        with connect_ws(server.url + f"?key={key}") as ws:
            code, reason = closed_reason(ws)
    assert refusing.asked == ["a", "b", "c"]
    assert code == 1008 and reason.startswith(
        "authorization refused: too many refused keys from your address; try again in"
    )
    assert any("3 keys refused from 127.0.0.1" in r.message for r in caplog.records)


class Faulty:
    """An authorizer with a bug: it raises something other than AuthError."""

    async def authorize(self, key: str, graph: str) -> Grant:
        raise TypeError("comparing strings with non-ASCII characters is not supported")


class Long:
    """An authorizer whose refusals are longer than a close frame carries."""

    async def authorize(self, key: str, graph: str) -> Grant:
        raise AuthError("this key is refused, and here is why, at great length: " + "é" * 100)


def test_a_faulty_authorizer_or_a_long_reason_still_closes_the_client_at_once(make_server, caplog):
    """An authorizer that crashes closes its client at once, saying the key could not be
    checked (the traceback is logged); a refusal longer than a close frame carries (123
    bytes) is cut to fit, rather than leaving the client hanging."""
    faulty = make_server(BridgeConfig(port=0, auth_timeout=30), authorizer=Faulty())
    with connect_ws(faulty.url) as ws:
        ws.send(json.dumps({"op": "auth", "key": "k"}))
        started = time.monotonic()
        code, reason = closed_reason(ws)
    assert time.monotonic() - started < 5
    assert (code, reason) == (
        1008,
        "authorization refused: the key could not be checked (a fault of the lab, logged)",
    )
    assert any(r.exc_info and r.exc_info[0] is TypeError for r in caplog.records)
    long = make_server(BridgeConfig(port=0, auth_timeout=30), authorizer=Long())
    with connect_ws(long.url + "?key=k") as ws:
        code, reason = closed_reason(ws)
    assert code == 1008 and reason.startswith("authorization refused: this key is refused")
    assert reason.endswith("é...") and len(reason.encode()) <= 123


class Revocable:
    """An authorizer whose keys can be withdrawn, or given more time, by the test."""

    def __init__(self) -> None:
        self.seconds = 60.0
        self.asked = 0
        self.away = False

    async def authorize(self, key: str, graph: str) -> Grant:
        self.asked += 1
        if self.away:
            raise AuthUnavailable("the authorizer could not be reached (ConnectError)")
        if self.seconds <= 0:
            raise AuthError("the lab knows no such key; fetch your slot's key again")
        return Grant(self.seconds, user="alice", ref="reservation:1")


def test_connected_keys_are_checked_again_and_a_withdrawn_one_disconnects(make_server):
    """Every key_recheck seconds the bridge asks again about a connected client's key: a
    new end moves the client's expiry; an authorizer away leaves the client connected;
    a refusal disconnects it, naming the robot and the reason."""
    revocable = Revocable()
    server = make_server(BridgeConfig(port=0, key_recheck=0.2), authorizer=revocable)
    with connect_ws(server.url) as ws:
        ws.send(json.dumps({"op": "auth", "key": "k"}))
        ws.send(json.dumps({"op": "call_service", "id": 1, "service": "/rosapi/nodes"}))
        frames_until(ws, lambda f: f.get("id") == 1)
        [conn] = server.lab.bridge.connections
        first = conn.session.expires_at
        revocable.seconds = 600.0
        server.wait_until(lambda: conn.session.expires_at > first + 500)
        revocable.away = True
        asked = revocable.asked
        server.wait_until(lambda: revocable.asked >= asked + 2)
        ws.send(json.dumps({"op": "call_service", "id": 2, "service": "/rosapi/nodes"}))
        frames_until(ws, lambda f: f.get("id") == 2)  # still connected
        revocable.away = False
        revocable.seconds = 0
        code, reason = closed_reason(ws)
    assert (code, reason) == (
        1008,
        "your key no longer opens playground: the lab knows no such key; fetch your slot's"
        " key again",
    )
