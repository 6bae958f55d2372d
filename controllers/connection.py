"""The client library's WebSocket: RFC 6455's client side on one blocking socket, read
and written on the caller's thread, with the standard library only.

A lockstep controller always knows when it waits for the lab, so nothing here runs on a
thread of its own: frames to send are kept until the caller reads (``flush``), so a
tick's commands and its ``/lab/step`` call leave in one write, and a tick's
observations and answer, which the lab sends in one write, are read in one.

It is written here rather than taken from ``websockets`` because a controller starts
once per trial: importing ``websockets`` took 29 ms of the 120 ms from a sandbox's
start to a controller's first step, most of it ``importlib.metadata`` for its version.
It speaks what the lab's bridge needs: text and binary messages, fragmented or not,
pings answered, the closing handshake, a limit on a message's size; no extensions
(the client offers none) and ``ws://`` only.

Inside a sandbox the lab's bridge is a unix socket (``$LAB_BRIDGE_SOCKET``); connecting
to it directly skips the relay that serves ``ws://127.0.0.1:9090`` there.
"""

from __future__ import annotations

import base64
import contextlib
import hashlib
import os
import socket
import struct
import time
from urllib.parse import urlsplit

READ = 2**20  # bytes read at a time
HANDSHAKE_LIMIT = 2**16  # bytes of HTTP response headers at most
ACCEPT_GUID = b"258EAFA5-E914-47DA-95CA-C5AB0DC85B11"  # RFC 6455, section 1.3

CONT, TEXT, BINARY, CLOSE, PING, PONG = 0x0, 0x1, 0x2, 0x8, 0x9, 0xA
NORMAL, PROTOCOL_ERROR, INVALID_DATA, TOO_BIG = 1000, 1002, 1007, 1009
_U16 = struct.Struct("!H")
_U64 = struct.Struct("!Q")


class WebSocketError(Exception):
    """Something went wrong with the WebSocket itself."""


class InvalidURI(WebSocketError):
    """A URL this client cannot connect to."""


class InvalidHandshake(WebSocketError):
    """The server did not answer with a WebSocket (an HTTP error, another protocol)."""


class ConnectionClosed(WebSocketError):
    """The connection is closed: ``code`` and ``reason`` are those of the server's close
    frame; without one, ``code`` is None and ``reason`` says what happened."""

    def __init__(self, code: int | None, reason: str) -> None:
        self.code = code
        self.reason = reason
        super().__init__(f"closed ({code}: {reason})" if code is not None else reason)


class _Failure(Exception):
    """What makes this side fail the connection: a close code and the reason."""

    def __init__(self, code: int, reason: str) -> None:
        self.code = code
        super().__init__(reason)


def mask(payload: bytes, key: bytes) -> bytes:
    """``payload`` XOR the 4-byte ``key`` repeated (RFC 6455, section 5.3), in C."""
    n = len(payload)
    if not n:
        return b""
    stream = (key * (n // 4 + 1))[:n]
    masked = int.from_bytes(payload, "little") ^ int.from_bytes(stream, "little")
    return masked.to_bytes(n, "little")


def frame(opcode: int, payload: bytes) -> bytes:
    """One final frame from a client: masked, as the protocol requires."""
    n = len(payload)
    if n < 126:
        head = bytes((0x80 | opcode, 0x80 | n))
    elif n < 1 << 16:
        head = bytes((0x80 | opcode, 0x80 | 126)) + _U16.pack(n)
    else:
        head = bytes((0x80 | opcode, 0x80 | 127)) + _U64.pack(n)
    key = os.urandom(4)
    return head + key + mask(payload, key)


class Connection:
    """A client WebSocket on a blocking socket, for one thread."""

    def __init__(self, sock: socket.socket, max_size: int | None) -> None:
        self._sock = sock
        self._max_size = max_size
        self._out: list[bytes] = []
        self._buffer = bytearray()
        self._parts: list[bytes] = []  # a fragmented message so far
        self._size = 0  # its bytes so far
        self._text = True
        self._messages: list[str | bytes] = []
        self._closing = False  # this side sent its close frame
        self._closed: ConnectionClosed | None = None  # why it is closed, once it is

    @classmethod
    def open(
        cls, url: str, *, unix: str | None = None, timeout: float = 10.0, max_size: int | None
    ) -> Connection:
        """Connect to ``url`` (over the unix socket ``unix`` if given) and shake hands.
        ``OSError``, ``TimeoutError``, ``InvalidURI`` or ``InvalidHandshake`` if not."""
        parts = urlsplit(url)
        if parts.scheme != "ws":
            raise InvalidURI(f"{url} is not a ws:// URL: the lab's client speaks ws:// only")
        try:
            host, port = parts.hostname, parts.port or 80
        except ValueError as err:  # a port that is not a number
            raise InvalidURI(f"{url}: {err}") from None
        if not host:
            raise InvalidURI(f"{url} names no host")
        if unix is not None:
            sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            address: str | tuple[str, int] = unix
        else:
            sock = socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET)
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            address = (host, port)
        try:
            sock.settimeout(timeout)
            sock.connect(address)
            connection = cls(sock, max_size)
            resource = (parts.path or "/") + (f"?{parts.query}" if parts.query else "")
            netloc = parts.netloc.rsplit("@", 1)[-1]
            connection._handshake(netloc, resource, time.monotonic() + timeout)
        except BaseException:
            sock.close()
            raise
        return connection

    def _handshake(self, host: str, resource: str, deadline: float) -> None:
        key = base64.b64encode(os.urandom(16)).decode()
        request = (
            f"GET {resource} HTTP/1.1\r\nHost: {host}\r\nUpgrade: websocket\r\n"
            f"Connection: Upgrade\r\nSec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n"
            "User-Agent: labd-controllers\r\n\r\n"
        )
        self._sock.sendall(request.encode())
        while b"\r\n\r\n" not in self._buffer:
            if len(self._buffer) > HANDSHAKE_LIMIT:
                raise InvalidHandshake("the server's answer has over 64 KiB of headers")
            data = self._recv(deadline)
            if not data:
                raise InvalidHandshake("the server closed the connection during the handshake")
            self._buffer += data
        head, _, rest = bytes(self._buffer).partition(b"\r\n\r\n")
        self._buffer = bytearray(rest)  # frames the server sent right after its answer
        lines = head.decode("latin-1").split("\r\n")
        status = lines[0].split(" ", 2)
        if len(status) < 2 or not status[0].startswith("HTTP/"):
            raise InvalidHandshake(f"the server did not answer in HTTP: {lines[0][:80]!r}")
        if status[1] != "101":
            said = " ".join(status[1:])
            raise InvalidHandshake(f"server rejected WebSocket connection: HTTP {said}")
        headers: dict[str, str] = {}
        for line in lines[1:]:
            name, _, value = line.partition(":")
            headers[name.strip().lower()] = value.strip()
        digest = hashlib.sha1(key.encode() + ACCEPT_GUID, usedforsecurity=False).digest()
        accept = base64.b64encode(digest).decode()  # what RFC 6455 asks: not a secret
        if headers.get("upgrade", "").lower() != "websocket":
            raise InvalidHandshake("the server's answer does not upgrade to a WebSocket")
        if "upgrade" not in headers.get("connection", "").lower():
            raise InvalidHandshake("the server's answer lacks Connection: Upgrade")
        if headers.get("sec-websocket-accept") != accept:
            raise InvalidHandshake("the server's Sec-WebSocket-Accept does not match the key")
        if headers.get("sec-websocket-extensions"):
            raise InvalidHandshake("the server chose an extension this client did not offer")
        if self._buffer:  # frames that came in the same read as the answer
            self._take()

    def send(self, text: str) -> None:
        """Queue a text message; it leaves at the next ``flush`` (or read)."""
        if self._closed is not None:
            raise self._closed
        self._out.append(frame(TEXT, text.encode()))

    def flush(self) -> None:
        """Write what is queued, in one write."""
        if not self._out:
            return
        data, self._out = b"".join(self._out), []
        try:
            self._sock.sendall(data)
        except OSError as err:
            self._lost(err)

    def recv(self, timeout: float) -> str | bytes:
        """The next message (what is queued is written first). ``TimeoutError`` after
        ``timeout`` seconds; ``ConnectionClosed`` once the connection is closed."""
        self.flush()
        deadline = time.monotonic() + timeout
        while not self._messages:
            if self._closed is not None:
                raise self._closed
            self._read(deadline)
        return self._messages.pop(0)

    def _recv(self, deadline: float) -> bytes:
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            raise TimeoutError
        self._sock.settimeout(remaining)
        return self._sock.recv(READ)

    def _read(self, deadline: float) -> None:
        """Read once from the socket and take in every whole frame it completes."""
        try:
            data = self._recv(deadline)
        except TimeoutError:
            raise
        except OSError as err:
            self._lost(err)
        if not data:
            self._finish(ConnectionClosed(None, "the connection ended without a close frame"))
            return
        self._buffer += data
        self._take()

    def _take(self) -> None:
        """Take in every whole frame the buffer holds, and answer what needs it."""
        try:
            self._frames()
        except _Failure as failure:  # this side fails the connection, saying why
            if not self._closing:
                self._out.append(frame(CLOSE, _U16.pack(failure.code)))
                self._closing = True
            self._finish(ConnectionClosed(None, str(failure)))
        self.flush()  # pongs, the close handshake

    def _frames(self) -> None:
        buffer = self._buffer
        position = 0
        while self._closed is None:
            if len(buffer) - position < 2:
                break
            first, second = buffer[position], buffer[position + 1]
            length, start = second & 0x7F, position + 2
            if length == 126:
                if len(buffer) - start < 2:
                    break
                (length,) = _U16.unpack_from(buffer, start)
                start += 2
            elif length == 127:
                if len(buffer) - start < 8:
                    break
                (length,) = _U64.unpack_from(buffer, start)
                start += 8
            if first & 0x70 or second & 0x80:
                raise _Failure(PROTOCOL_ERROR, "the server sent a malformed frame")
            if self._max_size is not None and self._size + length > self._max_size:
                raise _Failure(TOO_BIG, f"the server sent a message over {self._max_size} bytes")
            if len(buffer) - start < length:
                break
            payload = bytes(buffer[start : start + length])
            position = start + length
            self._frame(bool(first & 0x80), first & 0x0F, payload)
        del buffer[:position]

    def _frame(self, fin: bool, opcode: int, payload: bytes) -> None:
        if opcode >= CLOSE:
            if not fin or len(payload) > 125:
                raise _Failure(PROTOCOL_ERROR, "the server sent a malformed frame")
            if opcode == PING:
                self._out.append(frame(PONG, payload))
            elif opcode == CLOSE:
                self._close_received(payload)
            elif opcode != PONG:
                raise _Failure(PROTOCOL_ERROR, f"the server sent an unknown opcode {opcode}")
            return
        if opcode in (TEXT, BINARY):
            if self._parts:
                raise _Failure(PROTOCOL_ERROR, "the server began a message inside another")
            self._text = opcode == TEXT
        elif opcode != CONT or not self._parts:
            raise _Failure(PROTOCOL_ERROR, f"the server sent an unexpected opcode {opcode}")
        self._parts.append(payload)
        self._size += len(payload)
        if fin:
            data, self._parts, self._size = b"".join(self._parts), [], 0
            if not self._text:
                self._messages.append(data)
                return
            try:
                self._messages.append(data.decode())
            except UnicodeDecodeError:
                raise _Failure(INVALID_DATA, "the server sent text that is not UTF-8") from None

    def _close_received(self, payload: bytes) -> None:
        code, reason = None, ""
        if len(payload) >= 2:
            (code,) = _U16.unpack_from(payload)
            reason = payload[2:].decode("utf-8", "replace")
        if not self._closing:  # answer with the same code, as the protocol asks
            self._out.append(frame(CLOSE, payload[:2]))
            self._closing = True
        self._finish(ConnectionClosed(code, reason))

    def _finish(self, closed: ConnectionClosed) -> None:
        if self._closed is None:
            self._closed = closed

    def _lost(self, err: OSError) -> None:
        self._finish(ConnectionClosed(None, f"the connection broke: {err}"))
        assert self._closed is not None
        raise self._closed from err

    def close(self) -> None:
        """Close the connection (the closing handshake, briefly), then the socket."""
        try:
            if self._closed is None and not self._closing:
                self._out.append(frame(CLOSE, _U16.pack(NORMAL)))
                self._closing = True
                self.flush()
                deadline = time.monotonic() + 1.0
                while self._closed is None:
                    self._read(deadline)
        except (OSError, ConnectionClosed, TimeoutError):
            pass  # closed by the other side meanwhile, or too slow to say goodbye
        finally:
            with contextlib.suppress(OSError):
                self._sock.close()


__all__ = ["Connection", "ConnectionClosed", "InvalidHandshake", "InvalidURI", "WebSocketError"]
