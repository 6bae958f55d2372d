"""The build step's proxy (sandbox/proxy.py) against real sockets: it reaches the
destinations it was given, by name and port, refuses everything else with a 403 and a log
line, keeps to its bounds, chains to the host's own proxy, and ends with its step."""

from __future__ import annotations

import asyncio
import base64
import logging
import shutil
import socket
import tempfile
from collections.abc import AsyncIterator, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from sandbox.proxy import Destination, ProxyLimits, RegistryProxy, _bypassed
from tests.sandbox.conftest import Upstream

WAIT = 10.0  # seconds any answer may take: far more than it does


@dataclass
class Origin:
    """A TCP server on 127.0.0.1: echoes a tunnel's bytes, or answers one HTTP request."""

    heads: list[bytes] = field(default_factory=list)  # HTTP request heads it was sent
    accepted: int = 0
    server: asyncio.Server | None = None

    @property
    def port(self) -> int:
        assert self.server is not None
        return int(self.server.sockets[0].getsockname()[1])

    async def handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.accepted += 1
        first = await reader.read(4096)
        if first.startswith(b"GET "):
            head = first
            while b"\r\n\r\n" not in head:
                head += await reader.read(4096)
            self.heads.append(head)
            writer.write(b"HTTP/1.1 200 OK\r\nContent-Length: 5\r\nConnection: close\r\n\r\nhello")
        else:
            while first:
                writer.write(first)
                await writer.drain()
                first = await reader.read(4096)
        writer.close()


@pytest.fixture
async def origin() -> AsyncIterator[Origin]:
    made = Origin()
    made.server = await asyncio.start_server(made.handle, "127.0.0.1", 0)
    yield made
    made.server.close()


@pytest.fixture
async def bystander() -> AsyncIterator[Origin]:
    """Another listener on the same machine, which nothing may reach."""
    made = Origin()
    made.server = await asyncio.start_server(made.handle, "127.0.0.1", 0)
    yield made
    made.server.close()


@pytest.fixture
def folder() -> Iterator[Path]:
    """A short folder for unix sockets (their paths are at most 107 bytes)."""
    made = Path(tempfile.mkdtemp(prefix="labd-proxy-test-"))
    yield made
    shutil.rmtree(made, ignore_errors=True)


def local(port: int) -> Destination:
    return Destination("127.0.0.1", port)


async def ask(proxy: RegistryProxy, request: bytes) -> tuple[bytes, bytes]:
    """Send ``request`` to the proxy; its answer's head and body, up to its end."""
    reader, writer = await asyncio.open_unix_connection(str(proxy.path))
    try:
        writer.write(request)
        answer = await asyncio.wait_for(reader.read(), WAIT)
    finally:
        writer.close()
    head, _, body = answer.partition(b"\r\n\r\n")
    return head + b"\r\n\r\n", body


async def tunnel(
    proxy: RegistryProxy, authority: str
) -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
    """An open CONNECT tunnel through the proxy to ``authority``."""
    reader, writer = await asyncio.open_unix_connection(str(proxy.path))
    writer.write(f"CONNECT {authority} HTTP/1.1\r\nHost: {authority}\r\n\r\n".encode())
    head = await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), WAIT)
    assert head.startswith(b"HTTP/1.1 200 "), head
    return reader, writer


async def test_a_tunnel_to_an_allowed_destination_carries_bytes_both_ways(
    origin: Origin, folder: Path
) -> None:
    """CONNECT to a configured host:port is a tunnel: what goes in comes back from the far
    end, and ending it on one side ends it on the other."""
    async with RegistryProxy(folder / "p.sock", [local(origin.port)]) as proxy:
        reader, writer = await tunnel(proxy, f"127.0.0.1:{origin.port}")
        writer.write(b"ping" * 10_000)
        assert await asyncio.wait_for(reader.readexactly(40_000), WAIT) == b"ping" * 10_000
        writer.write_eof()
        assert await asyncio.wait_for(reader.read(), WAIT) == b""
        writer.close()
    assert proxy.refused == []


@pytest.mark.parametrize(
    "request_for",
    [
        "CONNECT 127.0.0.1:{bystander} HTTP/1.1\r\n\r\n",
        "GET http://127.0.0.1:{bystander}/x.tgz HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n",
        "CONNECT 169.254.169.254:80 HTTP/1.1\r\n\r\n",
        "CONNECT localhost:{origin} HTTP/1.1\r\n\r\n",
        "CONNECT 0x7f.0.0.1:{origin} HTTP/1.1\r\n\r\n",
        "CONNECT [::1]:{origin} HTTP/1.1\r\n\r\n",
    ],
    ids=["other-port", "plain-get", "link-local", "same-port-other-name", "hex-loopback", "v6"],
)
async def test_everything_else_is_refused_with_a_403_and_a_log_line(
    origin: Origin,
    bystander: Origin,
    folder: Path,
    caplog: pytest.LogCaptureFixture,
    request_for: str,
) -> None:
    """The machine's other ports, a link-local address, and the configured port under
    another name than the configured one: a 403 saying why, a log line, nothing reached."""
    request = request_for.format(origin=origin.port, bystander=bystander.port)
    target = request.split(" ")[1]
    with caplog.at_level(logging.WARNING, logger="sandbox.proxy"):
        async with RegistryProxy(folder / "p.sock", [local(origin.port)]) as proxy:
            head, body = await ask(proxy, request.encode())
    assert head.startswith(b"HTTP/1.1 403 Forbidden\r\n"), head
    assert body.decode() == (f"the build step reaches only the configured registry, not {target}\n")
    assert proxy.refused == [target]
    assert f"refused {request.split(' ')[0]} {target}: not a configured registry" in caplog.text
    assert (origin.accepted, bystander.accepted) == (0, 0)


async def test_a_plain_request_is_forwarded_in_origin_form(origin: Origin, folder: Path) -> None:
    """GET http://host:port/... to a configured http registry reaches it as an origin
    request, without the proxy's own headers, and closes after the answer."""
    request = (
        f"GET http://127.0.0.1:{origin.port}/simple/six/?a=1 HTTP/1.1\r\n"
        f"Host: 127.0.0.1:{origin.port}\r\n"
        "Proxy-Authorization: Basic c2VjcmV0\r\n"
        "Proxy-Connection: keep-alive\r\n"
        "Connection: keep-alive, X-Private\r\n"
        "X-Private: 1\r\n"
        "Accept: text/html\r\n\r\n"
    )
    async with RegistryProxy(folder / "p.sock", [local(origin.port)]) as proxy:
        head, body = await ask(proxy, request.encode())
    assert head.startswith(b"HTTP/1.1 200 OK\r\n")
    assert body == b"hello"
    [sent] = origin.heads
    assert (
        sent
        == (
            f"GET /simple/six/?a=1 HTTP/1.1\r\nHost: 127.0.0.1:{origin.port}\r\n"
            "Accept: text/html\r\nConnection: close\r\n\r\n"
        ).encode()
    )


@pytest.mark.parametrize(
    ("request_bytes", "status"),
    [
        (b"CONNECT 127.0.0.1 HTTP/1.1\r\n\r\n", b"400"),
        (b"GET https://127.0.0.1/x HTTP/1.1\r\n\r\n", b"400"),
        (b"GET /x HTTP/1.1\r\n\r\n", b"400"),
        (b"hello\r\n\r\n", b"400"),
        (b"GET http://127.0.0.1/ HTTP/1.1\r\n" + b"X: " + b"y" * 2000 + b"\r\n\r\n", b"431"),
    ],
    ids=["connect-without-port", "https-url", "origin-form", "not-http", "head-too-large"],
)
async def test_malformed_requests_are_answered_and_nothing_is_reached(
    origin: Origin, folder: Path, request_bytes: bytes, status: bytes
) -> None:
    """What is not a proxy request, or is too large, gets its 4xx, and reaches nothing."""
    limits = ProxyLimits(head_bytes=1024)
    async with RegistryProxy(folder / "p.sock", [local(origin.port)], limits=limits) as proxy:
        head, _ = await ask(proxy, request_bytes)
    assert head.split(b" ")[1] == status, head
    assert origin.accepted == 0


async def test_connections_past_the_limit_are_answered_503(origin: Origin, folder: Path) -> None:
    """With two tunnels open and a limit of two, a third connection is a 503; once one
    has ended, a new one is served again."""
    limits = ProxyLimits(connections=2)
    async with RegistryProxy(folder / "p.sock", [local(origin.port)], limits=limits) as proxy:
        authority = f"127.0.0.1:{origin.port}"
        first, second = await tunnel(proxy, authority), await tunnel(proxy, authority)
        head, _ = await ask(proxy, f"CONNECT {authority} HTTP/1.1\r\n\r\n".encode())
        assert head.startswith(b"HTTP/1.1 503 "), head
        first[1].close()
        assert await asyncio.wait_for(first[0].read(), WAIT) == b""
        # The proxy counts the tunnel out just after it has passed on its end: a few
        # turns of its loop, in which another try may still be a 503.
        for _ in range(100):
            reader, writer = await asyncio.open_unix_connection(str(proxy.path))
            writer.write(f"CONNECT {authority} HTTP/1.1\r\n\r\n".encode())
            head = await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), WAIT)
            writer.close()
            if not head.startswith(b"HTTP/1.1 503 "):
                break
        assert head.startswith(b"HTTP/1.1 200 "), head
        second[1].close()


async def test_a_head_not_sent_in_time_is_a_408(origin: Origin, folder: Path) -> None:
    """A client that never finishes its request is answered 408 after the head's time."""
    limits = ProxyLimits(head_seconds=0.2)
    async with RegistryProxy(folder / "p.sock", [local(origin.port)], limits=limits) as proxy:
        head, _ = await ask(proxy, f"CONNECT 127.0.0.1:{origin.port} HTTP/1.1\r\n".encode())
    assert head.startswith(b"HTTP/1.1 408 "), head
    assert origin.accepted == 0


async def test_a_silent_tunnel_is_closed(origin: Origin, folder: Path) -> None:
    """A tunnel silent both ways for the idle time is closed by the proxy."""
    limits = ProxyLimits(idle_seconds=0.3)
    async with RegistryProxy(folder / "p.sock", [local(origin.port)], limits=limits) as proxy:
        reader, writer = await tunnel(proxy, f"127.0.0.1:{origin.port}")
        writer.write(b"still here")
        assert await asyncio.wait_for(reader.readexactly(10), WAIT) == b"still here"
        assert await asyncio.wait_for(reader.read(), WAIT) == b""
        writer.close()


async def test_closing_the_proxy_ends_its_tunnels_and_removes_its_socket(
    origin: Origin, folder: Path
) -> None:
    """The end of the step ends every connection it has open, and nothing listens after."""
    proxy = RegistryProxy(folder / "p.sock", [local(origin.port)])
    await proxy.start()
    reader, writer = await tunnel(proxy, f"127.0.0.1:{origin.port}")
    await proxy.close()
    assert await asyncio.wait_for(reader.read(), WAIT) == b""
    writer.close()
    assert not proxy.path.exists()


async def test_an_allowed_destination_that_does_not_listen_is_a_502(folder: Path) -> None:
    """The registry down is a 502 naming it, not a hang."""
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    async with RegistryProxy(folder / "p.sock", [local(port)]) as proxy:
        head, body = await ask(proxy, f"CONNECT 127.0.0.1:{port} HTTP/1.1\r\n\r\n".encode())
    assert head.startswith(b"HTTP/1.1 502 "), head
    assert body.startswith(f"127.0.0.1:{port} cannot be reached: ".encode()), body


async def test_tunnels_chain_to_the_hosts_proxy_with_its_credentials(
    origin: Origin, upstream: Upstream, folder: Path
) -> None:
    """Where the host goes through a proxy, a tunnel is a CONNECT to it, with the
    credentials its URL holds."""
    settings = {"https": f"http://lab%40site:p%3Ass@127.0.0.1:{upstream.port}"}
    async with RegistryProxy(folder / "p.sock", [local(origin.port)], settings) as proxy:
        reader, writer = await tunnel(proxy, f"127.0.0.1:{origin.port}")
        writer.write(b"through two proxies")
        assert await asyncio.wait_for(reader.readexactly(19), WAIT) == b"through two proxies"
        writer.close()
    token = base64.b64encode(b"lab@site:p:ss").decode()
    [head] = upstream.heads
    assert (
        head
        == (
            f"CONNECT 127.0.0.1:{origin.port} HTTP/1.1\r\nHost: 127.0.0.1:{origin.port}\r\n"
            f"Proxy-Authorization: Basic {token}\r\n\r\n"
        ).encode()
    )


async def test_plain_requests_chain_to_the_hosts_proxy_whole(
    origin: Origin, upstream: Upstream, folder: Path
) -> None:
    """A plain request goes to the host's http proxy with its whole URL."""
    settings = {"http": f"http://127.0.0.1:{upstream.port}"}
    url = f"http://127.0.0.1:{origin.port}/simple/"
    async with RegistryProxy(folder / "p.sock", [local(origin.port)], settings) as proxy:
        head, body = await ask(proxy, f"GET {url} HTTP/1.1\r\n\r\n".encode())
    assert head.startswith(b"HTTP/1.1 200 OK\r\n")
    assert body == b"hello"
    assert upstream.heads[0].startswith(f"GET {url} HTTP/1.1\r\n".encode())
    assert origin.heads[0].startswith(f"GET {url} HTTP/1.1\r\n".encode())


async def test_no_proxy_sends_a_destination_around_the_hosts_proxy(
    origin: Origin, upstream: Upstream, folder: Path
) -> None:
    """A destination NO_PROXY names is reached directly, as the host would."""
    settings = {"https": f"http://127.0.0.1:{upstream.port}", "no": "localhost,127.0.0.1"}
    async with RegistryProxy(folder / "p.sock", [local(origin.port)], settings) as proxy:
        reader, writer = await tunnel(proxy, f"127.0.0.1:{origin.port}")
        writer.write(b"direct")
        assert await asyncio.wait_for(reader.readexactly(6), WAIT) == b"direct"
        writer.close()
    assert upstream.heads == []


async def test_the_hosts_proxy_refusing_is_a_502(
    origin: Origin, upstream: Upstream, folder: Path
) -> None:
    """The host's proxy refusing a tunnel is a 502 that quotes its answer."""
    upstream.refuse = True
    settings = {"https": f"http://127.0.0.1:{upstream.port}"}
    async with RegistryProxy(folder / "p.sock", [local(origin.port)], settings) as proxy:
        request = f"CONNECT 127.0.0.1:{origin.port} HTTP/1.1\r\n\r\n"
        head, body = await ask(proxy, request.encode())
    assert head.startswith(b"HTTP/1.1 502 "), head
    assert b"'HTTP/1.1 407 Proxy Authentication Required'" in body
    assert origin.accepted == 0


@pytest.mark.parametrize(
    ("url", "expected"),
    [
        ("https://Registry.Example/", Destination("registry.example", 443)),
        ("http://registry.example./simple", Destination("registry.example", 80)),
        ("http://127.0.0.1:8080/simple", Destination("127.0.0.1", 8080)),
        ("https://[::1]:8443/", Destination("::1", 8443)),
        ("file:///opt/pypi/simple", None),
        ("https://registry.example:99999/", None),
        ("not a url", None),
    ],
)
def test_a_urls_destination_is_its_name_and_port(url: str, expected: Destination | None) -> None:
    """A registry's URL gives the name and port the proxy allows (default ports filled in);
    URLs of other schemes allow nothing."""
    assert Destination.of_url(url) == expected


@pytest.mark.parametrize(
    ("no_proxy", "bypassed"),
    [
        ("", False),
        ("*", True),
        ("example", True),
        ("xample", False),
        ("registry.example", True),
        (".example", True),
        ("other.example, registry.example:443", True),
        ("registry.example:80", False),
    ],
)
def test_no_proxy_is_read_as_the_host_reads_it(no_proxy: str, bypassed: bool) -> None:
    """NO_PROXY entries match the host or a domain it is in, with or without a port."""
    assert _bypassed(Destination("registry.example", 443), no_proxy) is bypassed
