"""Every per-client limit of the bridge, hit at its documented default.

docs/protocol.md promises each of these; tests elsewhere check most of the mechanisms
with small configured values, and these check the numbers themselves: the defaults of
``BridgeConfig`` as a lab runs with them. The protocol core is driven with strings
(no sockets) where that is enough; the frame sizes and a client that reads none of its
replies need a real server.
"""

from __future__ import annotations

import json
import logging
import socket
import time

import orjson
import pytest
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect as ws_connect

from labd.bridge.ops.fragments import Fragments
from labd.config import BridgeConfig, MiB

pytestmark = pytest.mark.integration
DEFAULT = BridgeConfig()


def status_client(connect, **kwargs):
    """A client of the protocol core at the default config that asked for statuses."""
    client = connect(**kwargs)
    client.send({"op": "set_level", "level": "info"})
    client.frames()  # "status level set to info"
    return client


def errors(frames) -> list[str]:
    return [f["msg"] for f in frames if f["op"] == "status" and f["level"] == "error"]


# -- counts -----------------------------------------------------------------------------------


def test_a_client_advertises_at_most_1000_topics(connect):
    """The 1,001st advertised topic is refused with a status; the 1,000 stand."""
    client = status_client(connect)
    for i in range(1001):
        client.send({"op": "advertise", "topic": f"/mine/t{i}", "type": "std_msgs/msg/String"})
    assert errors(client.frames()) == ["advertise: too many advertised topics (the limit is 1000)"]
    assert DEFAULT.max_publishers == 1000


def test_a_client_provides_at_most_200_services_and_200_actions(connect):
    """The 201st service and the 201st action a client provides are refused."""
    client = status_client(connect)
    for i in range(201):
        client.send(
            {"op": "advertise_service", "service": f"/s{i}", "type": "std_srvs/srv/Trigger"}
        )
        client.send(
            {
                "op": "advertise_action",
                "action": f"/a{i}",
                "type": "example_interfaces/action/Fibonacci",
            }
        )
    assert errors(client.frames()) == [
        "advertise_service: too many advertised services (the limit is 200)",
        "advertise_action: too many advertised actions (the limit is 200)",
    ]


def test_a_client_waits_on_at_most_1000_calls_and_1000_goals(connect):
    """With 1,000 calls and 1,000 goals unanswered, the next of each fails at once, saying why."""
    provider, caller = connect(), connect()
    provider.send({"op": "advertise_service", "service": "/never", "type": "std_srvs/srv/Trigger"})
    provider.send(
        {
            "op": "advertise_action",
            "action": "/forever",
            "type": "example_interfaces/action/Fibonacci",
        }
    )
    for i in range(1001):  # timeout 0: wait for ever
        caller.send({"op": "call_service", "service": "/never", "id": f"c{i}", "timeout": 0})
        caller.send(
            {"op": "send_action_goal", "action": "/forever", "id": f"g{i}", "args": {"order": 1}}
        )
    (call, goal) = caller.frames()
    assert call["id"] == "c1000" and call["result"] is False
    assert call["values"] == "too many calls waiting for an answer (the limit is 1000)"
    assert (goal["op"], goal["id"], goal["status"], goal["result"]) == (
        "action_result",
        "g1000",
        0,
        False,  # never accepted: status 0, as every refusal
    )
    assert goal["values"] == "too many goals in progress (the limit is 1000)"
    assert len(provider.frames()) == 2000  # the 1,000 of each that were taken reached it


def test_a_client_sends_at_most_16_messages_in_fragments_at_once(connect):
    """The 17th message begun in fragments is refused; the 16 stay open."""
    client = status_client(connect)
    for i in range(17):
        client.send({"op": "fragment", "id": f"m{i}", "data": "{", "num": 0, "total": 2})
    assert errors(client.frames()) == [
        "fragment: too many messages in fragments at once (the limit is 16)"
    ]
    assert len(client.session.capability(Fragments).assemblies) == 16


def test_a_message_in_fragments_is_at_most_16_mib(connect):
    """Fragments adding up to more than 16 MiB are dropped as soon as they do."""
    client = status_client(connect)
    part = "x" * (9 * MiB)
    client.send({"op": "fragment", "id": "big", "data": part, "num": 0, "total": 2})
    client.send({"op": "fragment", "id": "big", "data": part, "num": 1, "total": 2})
    assert errors(client.frames()) == [
        f"fragment: too many characters in one fragmented message (the limit is {16 * MiB})"
    ]
    assert client.session.capability(Fragments).assemblies == {}


def test_fragments_that_stop_coming_are_forgotten_after_30_s(connect, timers):
    """A message whose parts stop is kept 30 s, then dropped with a warning."""
    client = status_client(connect)
    client.send({"op": "fragment", "id": "x", "data": "{", "num": 0, "total": 2})
    timers.advance(29.9)
    assert client.frames() == [] and "x" in client.session.capability(Fragments).assemblies
    timers.advance(0.2)
    (warning,) = client.frames()
    assert "only 1 of 2 parts arrived" in warning["msg"]
    assert client.session.capability(Fragments).assemblies == {}


def test_a_client_has_10_s_to_authorize(connect, timers):
    """With an authorizer, a client that sends no key is closed after 10 s, not before."""
    client = connect(auth_required=True)
    timers.advance(9.9)
    assert client.transport.closed is None
    timers.advance(0.2)
    assert client.transport.closed == (1008, "no authorization in time")


def test_log_lines_are_limited_to_bursts_of_50_then_20_a_second(connect, timers):
    """A client flooding bad frames puts 50 lines on /rosout, then 20 a second."""
    listener, clumsy = connect(), connect()
    listener.send({"op": "subscribe", "topic": "/rosout", "type": "rcl_interfaces/msg/Log"})
    for _ in range(200):
        clumsy.send({"op": "subscribe", "topic": 5})
    assert len(listener.frames()) == 50
    timers.advance(1.0)
    for _ in range(200):
        clumsy.send({"op": "subscribe", "topic": 5})
    lines = [f["msg"]["msg"] for f in listener.frames()]
    assert len(lines) == 20 and all("subscribe.topic must be a string" in x for x in lines)


# -- what waits for a client -------------------------------------------------------------------


def test_a_stalled_stream_keeps_its_newest_100_messages(connect):
    """A subscriber that reads nothing holds the newest 100 messages of a stream by default."""
    sub, pub = connect(), connect()
    sub.send({"op": "subscribe", "topic": "/chatter", "type": "std_msgs/msg/String"})
    pub.send({"op": "advertise", "topic": "/chatter", "type": "std_msgs/msg/String"})
    for i in range(150):
        pub.send({"op": "publish", "topic": "/chatter", "msg": {"data": str(i)}})
    assert [f["msg"]["data"] for f in sub.frames()] == [str(i) for i in range(50, 150)]


def test_a_stalled_client_holds_at_most_32_mib_of_messages(connect):
    """1 MiB messages to a client that reads nothing: at most 32 MiB wait, the newest."""
    sub, pub = connect(), connect()
    frame = {
        "op": "subscribe",
        "topic": "/big",
        "type": "std_msgs/msg/String",
        "queue_length": 1000,
    }
    sub.send(frame)
    pub.send({"op": "advertise", "topic": "/big", "type": "std_msgs/msg/String"})
    for i in range(48):
        pub.send({"op": "publish", "topic": "/big", "msg": {"data": f"{i:02d}" + "y" * MiB}})
    outbox = sub.session.outbox
    assert 30 * MiB < outbox.pending_bytes <= 32 * MiB
    got = [f["msg"]["data"][:2] for f in sub.frames()]
    assert got == [f"{i:02d}" for i in range(48 - len(got), 48)] and len(got) >= 30


def raw_client(port: int) -> socket.socket:
    sock = socket.create_connection(("127.0.0.1", port))
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    sock.sendall(
        b"GET / HTTP/1.1\r\nHost: x\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
        b"Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n\r\n"
    )
    answer = b""
    while b"\r\n\r\n" not in answer:
        answer += sock.recv(1)
    assert b" 101 " in answer
    return sock


def send_frame(sock: socket.socket, payload: bytes) -> None:
    """One masked text frame (mask zero), as a client must send it."""
    n = len(payload)
    if n < 126:
        head = bytes([0x81, 0x80 | n])
    elif n < 1 << 16:
        head = bytes([0x81, 0x80 | 126]) + n.to_bytes(2, "big")
    else:
        head = bytes([0x81, 0x80 | 127]) + n.to_bytes(8, "big")
    sock.sendall(head + b"\x00\x00\x00\x00" + payload)


@pytest.mark.timeout(60)
def test_a_client_that_reads_no_replies_is_cut_off_past_32_mib(make_server, caplog):
    """Replies are never dropped: a client whose unread replies pass 32 MiB is closed (1008)."""
    caplog.set_level(logging.INFO, logger="labd.bridge.session")
    server = make_server(BridgeConfig(port=0))
    value = json.dumps("z" * MiB)
    with ws_connect(server.url, max_size=None) as setter:
        setter.send(json.dumps({"op": "call_service", "service": "/rosapi/set_param", "id": 1,
                                "args": {"name": "big", "value": value}}))  # fmt: skip
        assert json.loads(setter.recv(timeout=10))["result"] is True
    sock = raw_client(server.port)
    ask = orjson.dumps(
        {"op": "call_service", "service": "/rosapi/get_param", "args": {"name": "big"}}
    )
    for _ in range(40):  # 40 MiB of answers, none of them read
        send_frame(sock, ask)
    server.wait_until(lambda: not server.lab.bridge.connections, timeout=30)
    sock.close()
    assert "closing (1008 the client does not read its replies)" in caplog.text


@pytest.mark.timeout(60)
def test_frames_over_16_mib_are_refused_and_over_64_mib_close(make_server):
    """At the defaults: a 17 MiB frame gets an error status and the connection stays; a
    65 MiB frame closes it with 1009."""
    server = make_server(BridgeConfig(port=0))
    with ws_connect(server.url, max_size=None, close_timeout=30) as ws:
        ws.send(json.dumps({"op": "set_level", "level": "error"}))
        big = {"op": "publish", "topic": "/x", "msg": {"data": "x" * (17 * MiB)}, "id": "big"}
        ws.send(json.dumps(big))
        status = json.loads(ws.recv(timeout=30))  # the frame was not read: no id to echo
        assert (status["op"], status["level"]) == ("status", "error"), status
        assert f"over the limit of {16 * MiB}; it was dropped" in status["msg"], status
        ws.send(json.dumps({"op": "call_service", "service": "/rosapi/get_time", "id": "t"}))
        assert json.loads(ws.recv(timeout=30))["result"] is True
        began = time.monotonic()
        ws.send("x" * (65 * MiB))
        with pytest.raises(ConnectionClosed) as closed:
            ws.recv(timeout=30)
    assert closed.value.rcvd is not None and closed.value.rcvd.code == 1009
    assert time.monotonic() - began < 30
