"""Serving the API and pages with uvicorn, on a thread and an event loop of their own.

The robots, the bridge and the queue's workers share the lab's main event loop, whose
time the live robots need: a tick is due every 50 ms. Pages, the API and their
uploads and downloads run here instead, on the ``http`` thread, so rendering a page
never takes the robots' loop's time (measured before: 100 anonymous readers took a
live robot from 18 to 14 ticks a second). What the pages need of a live robot they ask
of the robots' loop (``labd.web.robots``), which answers between two ticks.

Each connection is held to what ``HttpConfig`` allows (``_Guarded``): a request's head
(its line and headers) must arrive within ``header_timeout`` of the connection or of
the request's first byte, else it gets a 408 and is closed (a slowloris client holds
a connection only so long), and one address may hold only so many connections at once.

The socket is bound before uvicorn starts, so port 0 works and the real port is known.
With a certificate (``labd serve --tls-cert``, the same as the bridge's) it serves
https://, and the session and CSRF cookies are marked Secure. uvicorn's own signal
handling is off: ``labd serve`` handles SIGINT and SIGTERM.
``X-Forwarded-For`` is believed only from the proxies the operator names
(``trusted_proxies``, ``labd serve --trusted-proxy``); by default from nobody, so a
client cannot pick the address the throttles count it under.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import socket
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import h11
import uvicorn
from uvicorn.protocols.http.h11_impl import H11Protocol

from labd.addresses import PerAddress, address_of
from labd.config import HttpConfig

log = logging.getLogger("labd.api.server")
START = 30.0  # seconds uvicorn may take to listen


class _Server(uvicorn.Server):
    @contextlib.contextmanager
    def capture_signals(self) -> Iterator[None]:
        yield


class HttpServer:
    """The HTTP API and pages of ``app``, served on their own thread and event loop."""

    def __init__(
        self,
        app: Any,
        host: str = "127.0.0.1",
        port: int = 8080,
        config: HttpConfig | None = None,
        *,
        trusted_proxies: tuple[str, ...] = (),
        tls: tuple[Path, Path] | None = None,
    ) -> None:
        self.app = app
        self.tls = tls  # (certificate, key), PEM: https://
        self.host = host
        self.port = port
        self.trusted_proxies = trusted_proxies
        self.config = config or HttpConfig()
        self.loop: asyncio.AbstractEventLoop | None = None  # the http thread's, once started
        self._server: _Server | None = None
        self._thread: threading.Thread | None = None
        self._failed: BaseException | None = None

    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        scheme = "https" if self.tls is not None else "http"
        return f"{scheme}://{host}:{self.port}"

    async def start(self) -> None:
        """Listen, and serve on the ``http`` thread; returns once it serves."""
        family = socket.AF_INET6 if ":" in self.host else socket.AF_INET
        # IPPROTO_TCP named, so that asyncio sets TCP_NODELAY on each connection: without
        # it a response's head and body wait on the client's delayed ACK (40 ms each).
        sock = socket.socket(family, socket.SOCK_STREAM, socket.IPPROTO_TCP)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind((self.host, self.port))
        except OSError:
            sock.close()
            raise
        sock.listen(1024)
        sock.setblocking(False)
        self.port = sock.getsockname()[1]
        config = uvicorn.Config(
            self.app,
            log_level="warning",
            log_config=None,  # uvicorn's records go to the lab's log, and its repeat limit
            lifespan="off",
            access_log=False,
            timeout_notify=5,
            timeout_keep_alive=int(self.config.keep_alive),
            http=guarded(self.config),
            ws="none",  # the bridge serves WebSockets, on its own port
            # uvicorn's default trusts X-Forwarded-For from 127.0.0.1 (or $FORWARDED_ALLOW_IPS)
            proxy_headers=bool(self.trusted_proxies),
            forwarded_allow_ips=list(self.trusted_proxies),
            ssl_certfile=self.tls[0] if self.tls else None,
            ssl_keyfile=self.tls[1] if self.tls else None,
        )
        server = self._server = _Server(config)
        self._thread = threading.Thread(
            target=self._serve, args=(server, sock), name="http", daemon=True
        )
        self._thread.start()
        waited = 0.0
        while not server.started:
            if not self._thread.is_alive():
                raise self._failed or RuntimeError("the HTTP server stopped as it started")
            if waited > START:
                server.should_exit = True
                raise RuntimeError(f"the HTTP server did not listen within {START:g} s")
            await asyncio.sleep(0.01)
            waited += 0.01
        log.info("HTTP API on %s", self.url())

    def _serve(self, server: _Server, sock: socket.socket) -> None:
        async def serve() -> None:
            self.loop = asyncio.get_running_loop()
            await server.serve(sockets=[sock])

        try:
            asyncio.run(serve())
        except BaseException as err:  # handed to start(), or logged once it served
            self._failed = err
            if server.started:
                log.exception("the HTTP server stopped")
        finally:
            sock.close()

    async def close(self) -> None:
        """Stop serving: requests under way finish first."""
        if self._server is None or self._thread is None:
            return
        self._server.should_exit = True
        await asyncio.to_thread(self._thread.join)
        self._server = None


def guarded(config: HttpConfig) -> type[H11Protocol]:
    """uvicorn's HTTP/1.1 protocol, held to ``config``: one class per server, whose
    connections share one count per address."""
    per_address = PerAddress(config.max_connections_per_address)
    return type("Guarded", (_Guarded,), {"limits": config, "per_address": per_address})


def _plain(status: str, text: str) -> bytes:
    """A whole response that closes the connection, written past uvicorn's own."""
    body = text.encode()
    head = f"HTTP/1.1 {status}\r\ncontent-type: text/plain; charset=utf-8\r\n"
    return head.encode() + b"connection: close\r\ncontent-length: %d\r\n\r\n" % len(body) + body


class _Guarded(H11Protocol):
    """A connection of the HTTP server with a deadline on each request's head, counted
    under its client's address."""

    limits: HttpConfig
    per_address: PerAddress
    _address: str | None = None
    _counted = False
    _head_timer: asyncio.TimerHandle | None = None

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self._address = address_of(transport.get_extra_info("peername"))
        if not self.per_address.take(self._address):
            limit = self.limits.max_connections_per_address
            transport.write(
                _plain(
                    "503 Service Unavailable",
                    f"{limit} connections from your address are open, as many as it may"
                    " hold; close one, or retry later\n",
                )
            )
            transport.close()
            return
        self._counted = True
        self._wait_for_head()

    def data_received(self, data: bytes) -> None:
        super().data_received(data)
        self._wait_for_head()

    def connection_lost(self, exc: Exception | None) -> None:
        self._stop_waiting()
        if self._counted:
            self._counted = False
            self.per_address.give(self._address)
        super().connection_lost(exc)

    def _wait_for_head(self) -> None:
        """Time the head of the request under way: from the connection, or from the
        first byte of the next request on a kept connection (an idle kept connection is
        uvicorn's keep-alive timeout's to close)."""
        waiting = self.conn.their_state is h11.IDLE and not self.transport.is_closing()
        if waiting and self._head_timer is None:
            self._head_timer = self.loop.call_later(self.limits.header_timeout, self._too_slow)
        elif not waiting:
            self._stop_waiting()

    def _stop_waiting(self) -> None:
        if self._head_timer is not None:
            self._head_timer.cancel()
            self._head_timer = None

    def _too_slow(self) -> None:
        self._head_timer = None
        if self.conn.their_state is not h11.IDLE or self.transport.is_closing():
            return
        if self.conn.our_state is h11.IDLE:
            seconds = self.limits.header_timeout
            self.transport.write(
                _plain(
                    "408 Request Timeout",
                    f"the request's line and headers did not arrive within {seconds:g} s\n",
                )
            )
        self.transport.close()
