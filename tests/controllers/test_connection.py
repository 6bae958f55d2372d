"""The client library's own WebSocket, against a scripted server speaking raw bytes.

What it sends is parsed by ``websockets``' server-side protocol, the reference; what it
receives is written byte by byte here, including what a server should never send.
The lab's real bridge is in ``test_client.py``.
"""

from __future__ import annotations

import base64
import hashlib
import socket
import struct
import threading
from collections.abc import Callable, Iterator

import pytest
from websockets.frames import Opcode
from websockets.protocol import Protocol, Side

from controllers.connection import (
    Connection,
    ConnectionClosed,
    InvalidHandshake,
    InvalidURI,
    frame,
    mask,
)

GUID = b"258EAFA5-E914-47DA-95CA-C5AB0DC85B11"
Script = Callable[[socket.socket, Protocol], None]


def server_frame(opcode: int, payload: bytes, *, fin: bool = True, masked: bool = False) -> bytes:
    """A frame as a server writes it (unmasked), or a wrong one (``masked``)."""
    n = len(payload)
    first = (0x80 if fin else 0) | opcode
    if n < 126:
        head = bytes((first, n | (0x80 if masked else 0)))
    elif n < 1 << 16:
        head = bytes((first, 126 | (0x80 if masked else 0))) + struct.pack("!H", n)
    else:
        head = bytes((first, 127 | (0x80 if masked else 0))) + struct.pack("!Q", n)
    return head + (b"\0\0\0\0" if masked else b"") + payload


def accept(request: bytes, status: str = "101 Switching Protocols", extra: str = "") -> bytes:
    key = next(
        line.split(b":", 1)[1].strip()
        for line in request.split(b"\r\n")
        if line.lower().startswith(b"sec-websocket-key")
    )
    answer = base64.b64encode(hashlib.sha1(key + GUID).digest()).decode()
    return (
        f"HTTP/1.1 {status}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
        f"Sec-WebSocket-Accept: {answer}\r\n{extra}\r\n"
    ).encode()


def received(sock: socket.socket, protocol: Protocol, count: int) -> list[object]:
    """The next ``count`` frames the client sent, parsed by websockets (which refuses a
    frame that is not masked, as a server must)."""
    frames: list[object] = []
    while len(frames) < count:
        data = sock.recv(65536)
        if not data:
            break
        protocol.receive_data(data)
        frames += protocol.events_received()
    return frames


@pytest.fixture
def serve() -> Iterator[Callable[..., str]]:
    """Start a one-connection server running a script after the handshake; its URL."""
    threads: list[threading.Thread] = []
    errors: list[BaseException] = []

    def start(script: Script, *, answer: Callable[[bytes], bytes] = accept) -> str:
        listener = socket.create_server(("127.0.0.1", 0))

        def run() -> None:
            with listener, listener.accept()[0] as sock:
                try:
                    request = b""
                    while b"\r\n\r\n" not in request:
                        request += sock.recv(4096)
                    sock.sendall(answer(request))
                    script(sock, Protocol(Side.SERVER))
                except BaseException as err:  # reported by the test
                    errors.append(err)

        thread = threading.Thread(target=run, daemon=True)
        thread.start()
        threads.append(thread)
        return f"ws://127.0.0.1:{listener.getsockname()[1]}/robots/x?key=1"

    yield start
    for thread in threads:
        thread.join(5)
    assert not errors, errors


def test_masking_is_its_own_inverse_and_frames_parse_as_websockets_does():
    """Frames of every length class (7-bit, 16-bit, 64-bit) parse, unmasked, as sent."""
    key = b"\x01\x02\x03\x04"
    assert mask(mask(b"hello world", key), key) == b"hello world"
    server = Protocol(Side.SERVER, max_size=None)
    for size in (0, 5, 125, 126, 70_000):
        payload = bytes(range(256)) * (size // 256) + bytes(size % 256)
        server.receive_data(frame(Opcode.BINARY.value, payload))
        (got,) = server.events_received()
        assert got.data == payload and got.fin


def test_messages_whole_and_fragmented_and_a_ping_answered(serve):
    """A text message, a binary one in three fragments with a ping between them, and the
    client's own message; the ping's pong carries its payload back."""

    def script(sock, protocol):
        sock.sendall(
            server_frame(0x1, "héllo".encode())
            + server_frame(0x2, b"ab", fin=False)
            + server_frame(0x9, b"are you there")
            + server_frame(0x0, b"", fin=False)
            + server_frame(0x0, b"cd")
        )
        pong, text = received(sock, protocol, 2)
        assert (pong.opcode, pong.data) == (Opcode.PONG, b"are you there")
        assert (text.opcode, text.data) == (Opcode.TEXT, b'{"op": "x"}')
        sock.sendall(server_frame(0x8, struct.pack("!H", 1000) + b"bye"))
        (close,) = received(sock, protocol, 1)
        assert close.opcode is Opcode.CLOSE

    connection = Connection.open(serve(script), timeout=5, max_size=None)
    assert connection.recv(5) == "héllo"
    assert connection.recv(5) == b"abcd"
    connection.send('{"op": "x"}')
    with pytest.raises(ConnectionClosed) as closed:
        connection.recv(5)
    assert (closed.value.code, closed.value.reason) == (1000, "bye")
    connection.close()


@pytest.mark.parametrize(
    ("sent", "code", "said"),
    [
        (server_frame(0x1, b"x" * 2000), 1009, "over 1000 bytes"),
        (server_frame(0x1, b"\xff\xfe"), 1007, "not UTF-8"),
        (server_frame(0x1, b"hi", masked=True), 1002, "malformed"),
        (server_frame(0x0, b"orphan"), 1002, "unexpected opcode"),
        (server_frame(0x1, b"a", fin=False) + server_frame(0x1, b"b"), 1002, "inside another"),
        (server_frame(0x9, b"p", fin=False), 1002, "malformed"),
    ],
)
def test_what_a_server_must_not_send_fails_the_connection_saying_why(serve, sent, code, said):
    """The client closes with the code the protocol names, and says what was wrong."""

    def script(sock, protocol):
        sock.sendall(sent)
        (close,) = received(sock, protocol, 1)
        assert close.opcode is Opcode.CLOSE and struct.unpack("!H", close.data[:2])[0] == code

    connection = Connection.open(serve(script), timeout=5, max_size=1000)
    with pytest.raises(ConnectionClosed, match=said) as closed:
        connection.recv(5)
    assert closed.value.code is None  # the server sent no close frame
    connection.close()


def test_a_connection_that_ends_without_a_close_frame_says_so(serve):
    connection = Connection.open(serve(lambda sock, protocol: None), timeout=5, max_size=None)
    with pytest.raises(ConnectionClosed, match="without a close frame"):
        connection.recv(5)
    with pytest.raises(ConnectionClosed):  # and so does every later use
        connection.send("late")
    connection.close()


@pytest.mark.parametrize(
    ("answer", "said"),
    [
        (lambda r: b"HTTP/1.1 404 Not Found\r\nContent-Length: 0\r\n\r\n", "HTTP 404 Not Found"),
        (lambda r: accept(r).replace(b"Sec-WebSocket-Accept: ", b"Sec-WebSocket-Accept: x"),
         "does not match the key"),
        (lambda r: accept(r, extra="Sec-WebSocket-Extensions: permessage-deflate\r\n"),
         "did not offer"),
        (lambda r: b"SSH-2.0-OpenSSH\r\n\r\n", "did not answer in HTTP"),
    ],
)  # fmt: skip
def test_a_handshake_that_is_not_a_websocket_is_refused_naming_why(serve, answer, said):
    url = serve(lambda sock, protocol: None, answer=answer)
    with pytest.raises(InvalidHandshake, match=said):
        Connection.open(url, timeout=5, max_size=None)


def test_urls_it_cannot_use_are_refused():
    for url, said in (("wss://lab.example/", "ws:// only"), ("ws://:80/", "no host")):
        with pytest.raises(InvalidURI, match=said):
            Connection.open(url, timeout=1, max_size=None)
