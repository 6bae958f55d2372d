"""The WebSocket server for real: authorization over HTTP, TLS, limits, keepalive, isolation."""

from __future__ import annotations

import http.server
import json
import socket
import ssl
import threading
import time
from collections.abc import Iterator
from typing import ClassVar
from urllib.parse import parse_qs, urlsplit

import orjson
import pytest
import trustme
from websockets.exceptions import ConnectionClosed, InvalidStatus
from websockets.sync.client import ClientConnection, connect

from labd.config import BridgeConfig

pytestmark = pytest.mark.integration
WAIT = 10.0


def call(ws: ClientConnection, service: str, call_id: str = "c") -> dict:
    ws.send(orjson.dumps({"op": "call_service", "id": call_id, "service": service}).decode())
    while True:
        frame = orjson.loads(ws.recv(timeout=WAIT))
        if frame.get("id") == call_id:
            return frame


def raw_client(port: int, rcvbuf: int | None = None) -> socket.socket:
    """A WebSocket client that completes the handshake and then does nothing by itself."""
    sock = socket.socket()
    if rcvbuf is not None:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
    sock.connect(("127.0.0.1", port))
    sock.sendall(
        b"GET / HTTP/1.1\r\nHost: x\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
        b"Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n\r\n"
    )
    assert b" 101 " in sock.recv(4096)
    return sock


def send_frame(sock: socket.socket, payload: bytes) -> None:
    """Send one masked text frame (under 64 KiB), as a client must, on a raw socket."""
    length = bytes([0x80 | 126]) + len(payload).to_bytes(2, "big")
    sock.sendall(bytes([0x81]) + length + b"\x00\x00\x00\x00" + payload)


# -- a real HTTP authorizer ----------------------------------------------------------------


class _Authorizer(http.server.BaseHTTPRequestHandler):
    answers: ClassVar[dict[str, tuple[int, bytes]]] = {
        "good": (200, b'{"seconds": 30}'),
        "short": (200, b'{"seconds": 0.5}'),
        "jsonp": (200, b'authorize({"seconds": 30});'),
        "zero": (200, b'{"seconds": 0}'),
        "bad": (403, b"no"),
    }

    def do_GET(self) -> None:
        key = parse_qs(urlsplit(self.path).query).get("key", [""])[0]
        status, body = self.answers.get(key, (404, b"unknown"))
        self.send_response(status)
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    def log_message(self, *args: object) -> None:
        pass


@pytest.fixture
def authorizer_url() -> Iterator[str]:
    httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), _Authorizer)
    thread = threading.Thread(target=httpd.serve_forever, daemon=True)
    thread.start()
    yield f"http://127.0.0.1:{httpd.server_address[1]}/api/auth"
    httpd.shutdown()
    httpd.server_close()


@pytest.fixture
def guarded(make_server, authorizer_url):
    return make_server(BridgeConfig(port=0, authorizer_url=authorizer_url, auth_timeout=5))


@pytest.mark.parametrize("key", ["good", "jsonp"])
def test_auth_frame_with_a_valid_key_opens_the_bridge(guarded, key):
    """A first frame carrying a key the authorizer accepts (JSON or JSONP) opens the bridge."""
    with connect(guarded.url) as ws:
        ws.send(orjson.dumps({"op": "auth", "key": key}).decode())
        assert call(ws, "/rosapi/get_ros_version")["result"] is True


def test_key_in_the_url_query(guarded):
    """A key in the URL (?key=) needs no auth frame."""
    with connect(guarded.url + "/?key=good") as ws:
        assert call(ws, "/rosapi/get_ros_version")["result"] is True


@pytest.mark.parametrize("key", ["bad", "zero", "unknown"])
def test_refused_keys_close_the_connection(guarded, key):
    """A key the authorizer refuses closes the connection with 1008 and a reason."""
    with connect(guarded.url) as ws:
        ws.send(orjson.dumps({"op": "auth", "key": key}).decode())
        with pytest.raises(ConnectionClosed) as info:
            ws.recv(timeout=WAIT)
    assert info.value.rcvd is not None and info.value.rcvd.code == 1008
    assert "authorization refused" in info.value.rcvd.reason


def test_other_first_frame_closes(guarded):
    """Without an auth frame first, the connection is closed."""
    with connect(guarded.url) as ws:
        ws.send(orjson.dumps({"op": "call_service", "service": "/rosapi/nodes"}).decode())
        with pytest.raises(ConnectionClosed) as info:
            ws.recv(timeout=WAIT)
    assert info.value.rcvd is not None and info.value.rcvd.code == 1008


def test_connection_closes_when_its_time_runs_out(guarded):
    """A key good for half a second gives a connection that closes after about that long."""
    with connect(guarded.url + "/?key=short") as ws:
        started = time.monotonic()
        assert call(ws, "/rosapi/get_ros_version")["result"] is True
        with pytest.raises(ConnectionClosed) as info:
            while True:
                ws.recv(timeout=WAIT)
    assert info.value.rcvd is not None and "expired" in info.value.rcvd.reason
    assert time.monotonic() - started < 5


def test_unreachable_authorizer_refuses(make_server):
    """If the authorizer cannot be reached, the key is refused rather than let through."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        dead = f"http://127.0.0.1:{s.getsockname()[1]}/auth"
    server = make_server(BridgeConfig(port=0, authorizer_url=dead))
    with connect(server.url + "/?key=good") as ws, pytest.raises(ConnectionClosed) as info:
        ws.recv(timeout=WAIT)
    assert info.value.rcvd is not None and "could not be reached" in info.value.rcvd.reason


# -- TLS ---------------------------------------------------------------------------------


def test_tls(make_server, tmp_path):
    """Given a certificate and key, the bridge speaks wss:// and clients trusting it connect."""
    ca = trustme.CA()
    cert = ca.issue_cert("127.0.0.1", "localhost")
    cert_file, key_file = tmp_path / "cert.pem", tmp_path / "key.pem"
    cert.cert_chain_pems[0].write_to_path(cert_file)
    cert.private_key_pem.write_to_path(key_file)
    server = make_server(BridgeConfig(port=0, tls_cert=cert_file, tls_key=key_file))
    assert server.url.startswith("wss://")
    context = ssl.create_default_context()
    ca.configure_trust(context)
    with connect(server.url, ssl=context) as ws:
        assert call(ws, "/rosapi/get_ros_version")["result"] is True
    with pytest.raises(ssl.SSLError), connect(server.url, ssl=ssl.create_default_context()):
        pass


# -- routes and limits --------------------------------------------------------------------------


def test_routes(server):
    """/ and /robots/NAME reach the same graph; an unknown robot is a 404 with the choices."""
    with connect(server.url + "/robots/playground") as ws:
        assert call(ws, "/rosapi/get_ros_version")["result"] is True
    with pytest.raises(InvalidStatus) as info, connect(server.url + "/robots/nope"):
        pass
    assert info.value.response.status_code == 404
    assert b"/robots/playground" in info.value.response.body


def test_connection_limit(make_server):
    """Past max_connections, new clients get 503 while the others carry on."""
    server = make_server(BridgeConfig(port=0, max_connections=2))
    with connect(server.url) as a, connect(server.url) as b:
        with pytest.raises(InvalidStatus) as info, connect(server.url):
            pass
        assert info.value.response.status_code == 503
        assert call(a, "/rosapi/nodes")["result"] and call(b, "/rosapi/nodes")["result"]


def test_oversized_frames(make_server):
    """A frame over the message limit is refused with a status; one over the frame limit closes."""
    server = make_server(BridgeConfig(port=0, max_message_size=10_000, max_frame_size=50_000))
    with connect(server.url, max_size=None) as ws:
        ws.send(orjson.dumps({"op": "set_level", "level": "error"}).decode())
        ws.send(json.dumps({"op": "publish", "topic": "/x", "msg": {"data": "x" * 20_000}}))
        status = orjson.loads(ws.recv(timeout=WAIT))
        assert status["op"] == "status" and "over the limit" in status["msg"]
        assert call(ws, "/rosapi/nodes")["result"] is True
        ws.send("x" * 60_000)
        with pytest.raises(ConnectionClosed) as info:
            ws.recv(timeout=WAIT)
    assert info.value.rcvd is not None and info.value.rcvd.code == 1009


def test_keepalive_drops_a_silent_peer(make_server):
    """A peer that stops answering pings is disconnected and its subscriptions released."""
    config = BridgeConfig(port=0, ping_interval=0.2, ping_timeout=0.2, close_timeout=0.5)
    server = make_server(config)
    topics = server.lab.graphs["playground"].topics
    sock = raw_client(server.port)
    frame = orjson.dumps({"op": "subscribe", "topic": "/heard", "type": "std_msgs/String"})
    send_frame(sock, frame)  # then it never reads again, never answers a ping
    # Its subscription shows it connected: what follows is the keepalive's doing.
    server.wait_until(lambda: "/heard" in topics and len(topics["/heard"].subscriptions) == 1)
    server.wait_until(lambda: not server.lab.bridge.connections and "/heard" not in topics)
    sock.close()


def test_stalled_reader_does_not_hold_back_others(make_server):
    """A subscriber that never reads keeps bounded memory and the others keep getting messages."""
    server = make_server(BridgeConfig(port=0, max_queue_bytes=200_000))
    frame = orjson.dumps({"op": "subscribe", "topic": "/blob", "type": "std_msgs/String"})
    stalled = raw_client(server.port, rcvbuf=4096)
    send_frame(stalled, frame)
    with connect(server.url) as healthy, connect(server.url) as talker:
        healthy.send(frame.decode())
        topics = server.lab.graphs["playground"].topics
        server.wait_until(lambda: "/blob" in topics and len(topics["/blob"].subscriptions) == 2)
        advertise = {"op": "advertise", "topic": "/blob", "type": "std_msgs/String"}
        talker.send(orjson.dumps(advertise).decode())
        payload = "y" * 50_000
        for i in range(200):
            publish = {"op": "publish", "topic": "/blob", "msg": {"data": f"{i}{payload}"}}
            talker.send(orjson.dumps(publish).decode())
            got = orjson.loads(healthy.recv(timeout=WAIT))
            assert got["msg"]["data"].startswith(str(i))
        pending = server.call(
            lambda: max(c.session.outbox.pending_bytes for c in server.lab.bridge.connections)
        )
        assert pending <= 200_000
    stalled.close()
