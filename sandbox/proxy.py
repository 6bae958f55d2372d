"""The build step's only way out: an HTTP proxy that reaches the configured registry alone.

An install step (pip's, npm's) runs with no network of its own: its sandbox has only a
loopback of its own. Its launcher relays ``127.0.0.1:3128`` inside to a unix socket bound
into the sandbox, on which the lab serves this proxy for as long as the step lasts. It
takes two kinds of request:

    CONNECT host:port HTTP/1.1            a tunnel (https: TLS stays end to end)
    GET http://host:port/path HTTP/1.1    plain http (forwarded with Connection: close)

to the ``(host, port)`` pairs it was given, and answers anything else ``403`` with a line
saying why, logged, and kept in ``refused`` so that the step's error can name it.
Destinations are matched by the name and port written in the configured registry's URL,
never by the address a name resolves to: an address is not a registry, and the
registry's own name may resolve anywhere (a mirror on a private network, say). So the
lab machine's loopback, link-local and other addresses are out of reach unless the
operator named one of them as the registry.

Where the host itself reaches a registry through a proxy (``HTTPS_PROXY``, ``HTTP_PROXY``
and ``NO_PROXY``, as ``urllib.request.getproxies_environment()`` reads them), this proxy
chains to it: a tunnel is a CONNECT to that proxy, a plain request is forwarded to it.

Bounds, all in ``ProxyLimits``: connections at once (more are answered 503), the bytes
and seconds of a request's head, the seconds to reach a destination, and the seconds a
connection may stay silent both ways. ``close()`` (the end of the step) ends every
connection.

    Refusal          a request answered with an error status instead of being carried
"""

from __future__ import annotations

import asyncio
import base64
import contextlib
import logging
import urllib.parse
import uuid
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType

log = logging.getLogger(__name__)

CHUNK = 64 * 1024  # bytes relayed at a time
_HOP_BY_HOP = frozenset(
    {
        "connection",
        "keep-alive",
        "proxy-authenticate",
        "proxy-authorization",
        "proxy-connection",
        "te",
        "trailer",
        "upgrade",
    }
)
_DEFAULT_PORTS = {"http": 80, "https": 443}
_REASONS = {
    400: "Bad Request",
    403: "Forbidden",
    408: "Request Timeout",
    431: "Request Header Fields Too Large",
    502: "Bad Gateway",
    503: "Service Unavailable",
    504: "Gateway Timeout",
}


@dataclass(frozen=True)
class ProxyLimits:
    """What one step's proxy allows (seconds, bytes, connections)."""

    connections: int = 32  # open at once; npm opens up to 16 (its ``maxsockets``)
    head_bytes: int = 16 * 1024  # a request's line and headers
    head_seconds: float = 30.0  # to send them
    connect_seconds: float = 30.0  # to reach a destination (and the host's proxy's answer)
    idle_seconds: float = 120.0  # silent both ways, then the connection is closed


@dataclass(frozen=True, order=True)
class Destination:
    """A host name (or address, as written) and a port."""

    host: str
    port: int

    @classmethod
    def of_url(cls, url: str) -> Destination | None:
        """Where an http(s) URL leads; None for any other scheme (``file://``)."""
        parts = urllib.parse.urlsplit(url.strip())
        if parts.scheme not in _DEFAULT_PORTS or not parts.hostname:
            return None
        try:
            port = parts.port
        except ValueError:
            return None
        return cls(_normal(parts.hostname), port or _DEFAULT_PORTS[parts.scheme])

    @classmethod
    def of_authority(cls, authority: str) -> Destination:
        """``host:port`` (``[v6]:port``), as a CONNECT names it; ValueError otherwise."""
        parts = urllib.parse.urlsplit(f"//{authority}")
        if not parts.hostname or parts.port is None or parts.netloc != authority:
            raise ValueError(f"not host:port: {authority!r}")
        return cls(_normal(parts.hostname), parts.port)

    def __str__(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"{host}:{self.port}"


def _normal(host: str) -> str:
    return host.lower().rstrip(".")


class Refusal(Exception):
    """A request answered with ``status`` and ``message`` instead of being carried."""

    def __init__(self, status: int, message: str) -> None:
        self.status = status
        self.message = message
        super().__init__(f"{status} {message}")


@dataclass(frozen=True)
class _Upstream:
    """The host's own proxy: where to connect, and its credentials' header, if any."""

    destination: Destination
    authorization: str | None


@dataclass
class _Request:
    method: str
    target: str
    version: str
    headers: list[tuple[str, str]] = field(default_factory=list)


class RegistryProxy:
    """An HTTP proxy on the unix socket ``path`` that reaches ``allowed`` and nothing else.

    ``upstream`` is the host's proxy settings (``urllib.request.getproxies_environment()``:
    ``http``, ``https`` and ``no`` keys), empty when the host reaches registries directly.
    Use it as ``async with``: it serves from entry to exit, then ends every connection and
    removes its socket.
    """

    def __init__(
        self,
        path: Path,
        allowed: Iterable[Destination],
        upstream: Mapping[str, str] | None = None,
        limits: ProxyLimits | None = None,
    ) -> None:
        self.path = path
        self.allowed = frozenset(allowed)
        self.upstream = dict(upstream or {})
        self.limits = limits or ProxyLimits()
        self.refused: list[str] = []  # what the step asked for and did not get, in order
        self.id = f"proxy-{uuid.uuid4().hex[:8]}"
        self._server: asyncio.Server | None = None
        self._tasks: set[asyncio.Task[None]] = set()  # every connection's, for close()
        self._carrying = 0  # connections past the limit check

    async def __aenter__(self) -> RegistryProxy:
        await self.start()
        return self

    async def __aexit__(
        self,
        kind: type[BaseException] | None,
        error: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        await self.close()

    async def start(self) -> None:
        """Listen on ``path``."""
        self._server = await asyncio.start_unix_server(
            self._serve, str(self.path), limit=self.limits.head_bytes
        )
        log.info(
            "[%s] serving the build step on %s; it may reach %s",
            self.id,
            self.path,
            ", ".join(map(str, sorted(self.allowed))) or "nothing",
        )

    async def close(self) -> None:
        """Stop listening, end every connection, remove the socket."""
        if self._server is not None:
            self._server.close()
        tasks = list(self._tasks)
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        if self._server is not None:
            await self._server.wait_closed()
            self._server = None
        with contextlib.suppress(FileNotFoundError):
            self.path.unlink()

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        """Serve a connection in a task of the proxy's own, which ``close()`` cancels.

        asyncio's task for the connection must end by itself: Python 3.11's streams log
        its cancellation as an error in a callback.
        """
        task = asyncio.get_running_loop().create_task(self._connection(reader, writer))
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)
        await asyncio.wait({task})

    async def _connection(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        counted = self._carrying < self.limits.connections
        self._carrying += counted
        try:
            if not counted:
                log.warning("[%s] refused a connection: %d open", self.id, self._carrying)
                await self._read_request(reader)  # read, so that no reset loses the answer
                raise Refusal(503, f"more than {self.limits.connections} connections at once")
            await self._handle(reader, writer)
        except Refusal as refusal:
            with contextlib.suppress(OSError):
                await _answer(writer, refusal.status, refusal.message)
        except (OSError, asyncio.IncompleteReadError) as err:
            log.debug("[%s] a connection ended: %s", self.id, err)
        finally:
            self._carrying -= counted
            writer.close()

    async def _handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        request = await self._read_request(reader)
        if request.method == "CONNECT":
            try:
                destination = Destination.of_authority(request.target)
            except ValueError:
                raise Refusal(400, "CONNECT takes host:port") from None
            self._check(destination, request.method, request.target)
            far_reader, far_writer = await self._tunnel(destination)
            writer.write(b"HTTP/1.1 200 Connection established\r\n\r\n")
        else:
            url = urllib.parse.urlsplit(request.target)
            found = Destination.of_url(request.target)
            if url.scheme != "http" or found is None:
                raise Refusal(400, "only CONNECT host:port, or a request for an http:// URL")
            self._check(found, request.method, request.target)
            far_reader, far_writer, head = await self._forward(found, request, url)
            far_writer.write(head)
        try:
            await self._relay(reader, writer, far_reader, far_writer)
        finally:
            far_writer.close()

    async def _read_request(self, reader: asyncio.StreamReader) -> _Request:
        limits = self.limits
        try:
            async with asyncio.timeout(limits.head_seconds):
                raw = await reader.readuntil(b"\r\n\r\n")
        except TimeoutError:
            raise Refusal(408, f"no request within {limits.head_seconds:g} s") from None
        except asyncio.LimitOverrunError:
            raise Refusal(431, f"a request's head is at most {limits.head_bytes} bytes") from None
        lines = raw.decode("latin-1").split("\r\n")[:-2]
        words = lines[0].split(" ")
        if len(words) != 3 or not words[2].startswith("HTTP/1."):
            raise Refusal(400, "not an HTTP/1 request")
        request = _Request(words[0], words[1], words[2])
        for line in lines[1:]:
            name, colon, value = line.partition(":")
            if not colon or not name.strip() or name != name.strip():
                raise Refusal(400, "a header line without a name")
            request.headers.append((name, value.strip()))
        return request

    def _check(self, destination: Destination, method: str, target: str) -> None:
        """Refuse (403, logged, remembered) what is not a configured registry."""
        if destination in self.allowed:
            return
        shown = "".join(c if c.isprintable() else "?" for c in target)[:200]
        self.refused.append(shown)
        log.warning("[%s] refused %s %s: not a configured registry", self.id, method, shown)
        raise Refusal(403, f"the build step reaches only the configured registry, not {shown}")

    async def _tunnel(
        self, destination: Destination
    ) -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
        """A connection to ``destination``, directly or through the host's proxy."""
        upstream = self._upstream(destination, "https")
        if upstream is None:
            return await self._connect(destination)
        reader, writer = await self._connect(upstream.destination)
        head = f"CONNECT {destination} HTTP/1.1\r\nHost: {destination}\r\n"
        if upstream.authorization is not None:
            head += f"Proxy-Authorization: {upstream.authorization}\r\n"
        writer.write(f"{head}\r\n".encode("latin-1"))
        try:
            async with asyncio.timeout(self.limits.connect_seconds):
                answer = await reader.readuntil(b"\r\n\r\n")
        except (TimeoutError, asyncio.IncompleteReadError, asyncio.LimitOverrunError):
            writer.close()
            raise Refusal(502, f"the host's proxy gave no answer for {destination}") from None
        status = answer.split(b"\r\n", 1)[0].decode("latin-1")
        if status.split(" ")[1:2] != ["200"]:
            writer.close()
            raise Refusal(502, f"the host's proxy answered {status!r} for {destination}")
        return reader, writer

    async def _forward(
        self, destination: Destination, request: _Request, url: urllib.parse.SplitResult
    ) -> tuple[asyncio.StreamReader, asyncio.StreamWriter, bytes]:
        """A connection for a plain request, and the head to send on it."""
        upstream = self._upstream(destination, "http")
        if upstream is None:
            target = urllib.parse.urlunsplit(("", "", url.path or "/", url.query, ""))
        else:
            target = request.target  # a proxy takes the whole URL
        connection = [v.strip().lower() for n, v in request.headers if n.lower() == "connection"]
        dropped = _HOP_BY_HOP | {word.strip() for v in connection for word in v.split(",")}
        headers = [(n, v) for n, v in request.headers if n.lower() not in dropped]
        if not any(n.lower() == "host" for n, _ in headers):
            headers.insert(0, ("Host", url.netloc))
        headers.append(("Connection", "close"))
        if upstream is not None and upstream.authorization is not None:
            headers.append(("Proxy-Authorization", upstream.authorization))
        lines = [f"{request.method} {target} {request.version}"]
        lines += [f"{name}: {value}" for name, value in headers]
        head = ("\r\n".join(lines) + "\r\n\r\n").encode("latin-1")
        reader, writer = await self._connect(upstream.destination if upstream else destination)
        return reader, writer, head

    def _upstream(self, destination: Destination, scheme: str) -> _Upstream | None:
        """The host's proxy for ``destination``, unless the host reaches it directly."""
        url = self.upstream.get(scheme)
        if not url or _bypassed(destination, self.upstream.get("no", "")):
            return None
        parts = urllib.parse.urlsplit(url if "://" in url else f"http://{url}")
        if parts.scheme != "http" or not parts.hostname:
            raise Refusal(502, f"the host's {scheme} proxy is not an http:// proxy")
        authorization = None
        if parts.username is not None:
            user = urllib.parse.unquote(parts.username)
            password = urllib.parse.unquote(parts.password or "")
            token = base64.b64encode(f"{user}:{password}".encode()).decode()
            authorization = f"Basic {token}"
        return _Upstream(Destination(parts.hostname, parts.port or 80), authorization)

    async def _connect(
        self, destination: Destination
    ) -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
        seconds = self.limits.connect_seconds
        try:
            async with asyncio.timeout(seconds):
                return await asyncio.open_connection(destination.host, destination.port)
        except TimeoutError:
            raise Refusal(504, f"{destination} did not answer within {seconds:g} s") from None
        except OSError as err:
            raise Refusal(502, f"{destination} cannot be reached: {err.strerror or err}") from None

    async def _relay(
        self,
        near_reader: asyncio.StreamReader,
        near_writer: asyncio.StreamWriter,
        far_reader: asyncio.StreamReader,
        far_writer: asyncio.StreamWriter,
    ) -> None:
        """Carry bytes both ways until both have ended, or both were silent too long."""
        loop = asyncio.get_running_loop()
        idle = self.limits.idle_seconds

        async def pump(source: asyncio.StreamReader, sink: asyncio.StreamWriter) -> None:
            try:
                while data := await source.read(CHUNK):
                    deadline.reschedule(loop.time() + idle)
                    sink.write(data)
                    await sink.drain()
                if sink.can_write_eof():
                    sink.write_eof()
            except OSError:  # one side broke: so does the other
                near_writer.transport.abort()
                far_writer.transport.abort()

        try:
            async with asyncio.timeout(idle) as deadline:
                await asyncio.gather(pump(near_reader, far_writer), pump(far_reader, near_writer))
        except TimeoutError:
            log.info("[%s] closed a connection silent for %g s", self.id, idle)


def _bypassed(destination: Destination, no_proxy: str) -> bool:
    """Whether ``NO_PROXY`` (``no_proxy``) sends ``destination`` around the host's proxy,
    read as urllib and requests read it: ``*``, or names (a leading dot or not) that are
    the host or a domain it is in, each with or without a port."""
    for entry in no_proxy.replace(" ", ",").split(","):
        name = entry.strip().lower().lstrip(".")
        if name == "*":
            return True
        if not name:
            continue
        if name.startswith("["):  # [v6] or [v6]:port
            host, _, rest = name[1:].partition("]")
            port = rest.removeprefix(":")
        elif name.count(":") == 1:
            host, _, port = name.partition(":")
        else:  # a name, or a bare v6 address
            host, port = name, ""
        if port.isdigit() and int(port) != destination.port:
            continue
        if destination.host == host or destination.host.endswith(f".{host}"):
            return True
    return False


async def _answer(writer: asyncio.StreamWriter, status: int, message: str) -> None:
    """Answer ``status`` with ``message`` as a line of text, and end the connection."""
    body = f"{message}\n".encode()
    head = (
        f"HTTP/1.1 {status} {_REASONS[status]}\r\n"
        "Content-Type: text/plain; charset=utf-8\r\n"
        f"Content-Length: {len(body)}\r\n"
        "Connection: close\r\n\r\n"
    )
    writer.write(head.encode("latin-1") + body)
    await writer.drain()
