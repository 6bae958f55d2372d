"""The client library's WebSocket: one blocking socket, read and written on the caller's
thread.

``websockets``' synchronous client reads its socket on a thread of its own and hands each
message to the caller's thread: two wake-ups per message, on top of the lab's. A lockstep
controller needs none of that: it always knows when it waits for the lab. So this drives
``websockets``' protocol object (its sans-I/O core: handshake, framing, masking, pings,
closing) over a plain socket: frames to send are kept until the caller reads (``flush``),
so a tick's commands and its ``/lab/step`` call leave in one write, and a tick's
observations and answer, which the lab sends in one write, are read in one.

Inside a sandbox the lab's bridge is a unix socket (``$LAB_BRIDGE_SOCKET``); connecting to
it directly skips the relay that serves ``ws://127.0.0.1:9090`` there.
"""

from __future__ import annotations

import contextlib
import socket
import time
from urllib.parse import urlsplit

from websockets.client import ClientProtocol
from websockets.exceptions import ConnectionClosed, InvalidHandshake, InvalidURI
from websockets.frames import Frame, Opcode
from websockets.http11 import Response
from websockets.protocol import State
from websockets.uri import parse_uri

READ = 2**20  # bytes read at a time


class Connection:
    """A client WebSocket on a blocking socket, for one thread."""

    def __init__(self, sock: socket.socket, protocol: ClientProtocol) -> None:
        self._sock = sock
        self._protocol = protocol
        self._out: list[bytes] = []
        self._parts: list[bytes] = []  # a fragmented message so far
        self._text = True
        self._messages: list[str | bytes] = []
        self._answered = False  # the server's handshake response has come

    @classmethod
    def open(
        cls, url: str, *, unix: str | None = None, timeout: float = 10.0, max_size: int | None
    ) -> Connection:
        """Connect to ``url`` (over the unix socket ``unix`` if given) and shake hands.
        ``OSError``, ``TimeoutError``, ``InvalidURI`` or ``InvalidHandshake`` if not."""
        uri = parse_uri(url)
        if unix is not None:
            sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            address: str | tuple[str, int] = unix
        else:
            parts = urlsplit(url)
            if parts.scheme != "ws":
                raise InvalidURI(url, "the lab's client speaks ws:// only")
            family = socket.AF_INET6 if ":" in uri.host else socket.AF_INET
            sock = socket.socket(family, socket.SOCK_STREAM)
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            address = (uri.host, uri.port)
        try:
            sock.settimeout(timeout)
            sock.connect(address)
            protocol = ClientProtocol(uri, max_size=max_size)
            connection = cls(sock, protocol)
            connection._handshake(time.monotonic() + timeout)
        except BaseException:
            sock.close()
            raise
        return connection

    def _handshake(self, deadline: float) -> None:
        protocol = self._protocol
        protocol.send_request(protocol.connect())
        self._out += protocol.data_to_send()
        self.flush()
        while not self._answered:
            self._read(deadline)
        if protocol.handshake_exc is not None:
            raise protocol.handshake_exc

    def send(self, text: str) -> None:
        """Queue a text message; it leaves at the next ``flush`` (or read)."""
        self._protocol.send_text(text.encode())
        self._out += self._protocol.data_to_send()

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
            self._read(deadline)
        return self._messages.pop(0)

    def _read(self, deadline: float) -> None:
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            raise TimeoutError
        self._sock.settimeout(remaining)
        try:
            data = self._sock.recv(READ)
        except TimeoutError:
            raise
        except OSError as err:
            self._lost(err)
        protocol = self._protocol
        if data:
            protocol.receive_data(data)
        else:
            protocol.receive_eof()
        for event in protocol.events_received():
            if isinstance(event, Frame):
                self._frame(event)
            elif isinstance(event, Response):
                self._answered = True
        self._out += protocol.data_to_send()  # pongs, the close handshake
        self.flush()
        if protocol.handshake_exc is not None:
            raise protocol.handshake_exc
        if protocol.state is State.CLOSED and not self._messages:
            raise protocol.close_exc

    def _frame(self, frame: Frame) -> None:
        if frame.opcode in (Opcode.TEXT, Opcode.BINARY):
            self._text = frame.opcode is Opcode.TEXT
            self._parts = [bytes(frame.data)]
        elif frame.opcode is Opcode.CONT:
            self._parts.append(bytes(frame.data))
        else:
            return  # ping, pong, close: the protocol object answers them
        if frame.fin:
            data, self._parts = b"".join(self._parts), []
            self._messages.append(data.decode() if self._text else data)

    def _lost(self, err: OSError) -> None:
        with contextlib.suppress(EOFError):  # (an end already seen)
            self._protocol.receive_eof()
        if self._protocol.state is State.CLOSED:
            raise self._protocol.close_exc from err
        raise ConnectionClosed(None, None) from err

    def _closed(self) -> bool:
        return self._protocol.state is State.CLOSED

    def close(self) -> None:
        """Close the connection (the closing handshake, briefly), then the socket."""
        try:
            if self._protocol.state is State.OPEN:
                self._protocol.send_close()
                self._out += self._protocol.data_to_send()
                self.flush()
                deadline = time.monotonic() + 1.0
                while not self._closed():
                    self._read(deadline)
        except (OSError, ConnectionClosed, TimeoutError):
            pass  # closed by the other side meanwhile, or too slow to say goodbye
        finally:
            self._sock.close()


__all__ = ["Connection", "ConnectionClosed", "InvalidHandshake", "InvalidURI"]
