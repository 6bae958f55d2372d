"""A crowd on a live robot: 200 WebSocket clients at once, half of them never reading.

`labd serve` hosts one live robot (``/robots/icreate-1``, its camera rendering while
anyone watches). A hundred healthy clients subscribe to its camera and odometry and
read everything; then a hundred more subscribe to the camera and never read a byte.
Beside the stalled ones, every healthy client goes on receiving the camera and
odometry, every message in order and the same messages as every other healthy client
(the bridge drops only for those who do not read); the server's memory stays bounded,
and the connection limit (200, the default) turns away the 201st client with a 503.

How fast the healthy clients receive, alone and beside the stalled ones, is measured
by ``bench/crowds.py`` and printed as a ratio: a rate depends on the machine.
"""

from __future__ import annotations

import asyncio
import bisect
import itertools
import socket
import threading
import time

import orjson
import pytest
from websockets.asyncio.client import ClientConnection, connect
from websockets.exceptions import InvalidStatus

from tests.helpers.timing import SECOND, eventually

pytestmark = [pytest.mark.integration, pytest.mark.rates]

HEALTHY = 100
STALLED = 100
MESSAGES = 40  # each healthy client's messages on each topic, before and beside the stalled
GROWTH = 150 * 1024 * 1024  # bytes the server may grow by with the stalled clients
CAMERA = "/camera/image/compressed"
TOPICS = {CAMERA: "sensor_msgs/msg/CompressedImage", "/odom": "nav_msgs/msg/Odometry"}


def stamp(message: dict[str, object]) -> int:
    """A message's ``header.stamp`` in nanoseconds (the robot's simulation time)."""
    header = message["msg"]["header"]  # type: ignore[index]
    return int(header["stamp"]["sec"]) * 1_000_000_000 + int(header["stamp"]["nanosec"])


class Healthy:
    """A client that subscribes to the camera and odometry and reads all it is sent;
    ``stamps`` holds each topic's message stamps in the order they came."""

    def __init__(self, ws: ClientConnection) -> None:
        self.ws = ws
        self.counts = dict.fromkeys(TOPICS, 0)
        self.stamps: dict[str, list[int]] = {topic: [] for topic in TOPICS}
        self.replies: asyncio.Queue[dict[str, object]] = asyncio.Queue()
        self.reader = asyncio.create_task(self._read())

    async def _read(self) -> None:
        async for frame in self.ws:
            message = orjson.loads(frame)
            if message["op"] == "publish":
                self.counts[message["topic"]] += 1
                self.stamps[message["topic"]].append(stamp(message))
            else:
                await self.replies.put(message)

    async def subscribe(self) -> None:
        for topic, type_name in TOPICS.items():
            await self.ws.send(
                orjson.dumps({"op": "subscribe", "topic": topic, "type": type_name}).decode()
            )

    async def call(self, service: str, args: dict[str, object] | None = None) -> dict[str, object]:
        frame = {"op": "call_service", "service": service, "args": args or {}, "id": service}
        await self.ws.send(orjson.dumps(frame).decode())
        return await asyncio.wait_for(self.replies.get(), 30 * SECOND)


def stalled_client(port: int, path: str) -> socket.socket:
    """A client that subscribes to the camera and then never reads (a tiny receive buffer)."""
    sock = socket.socket()
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    sock.connect(("127.0.0.1", port))
    sock.sendall(
        f"GET {path} HTTP/1.1\r\nHost: x\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
        "Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n\r\n".encode()
    )
    answer = b""
    while b"\r\n\r\n" not in answer:
        answer += sock.recv(1)  # byte by byte: nothing past the handshake is read
    assert b" 101 " in answer, answer
    frame = orjson.dumps({"op": "subscribe", "topic": CAMERA, "type": TOPICS[CAMERA]})
    mask = b"\x00\x00\x00\x00"
    sock.sendall(bytes([0x81, 0x80 | 126]) + len(frame).to_bytes(2, "big") + mask + frame)
    return sock


class Sampler:
    """The server's RSS, sampled every 0.2 s on a thread."""

    def __init__(self, lab) -> None:
        self.lab = lab
        self.samples: list[int] = []
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        while not self.stop.wait(0.2):
            self.samples.append(self.lab.rss())

    def close(self) -> int:
        self.stop.set()
        self.thread.join(5)
        return max(self.samples)


async def each_receives(clients: list[Healthy], count: int, what: str) -> dict[str, int]:
    """Wait until every client has received ``count`` messages on every topic newer
    than any client had seen when called (nobody starved); those newest stamps."""
    newest = {
        topic: max((c.stamps[topic][-1] for c in clients if c.stamps[topic]), default=-1)
        for topic in TOPICS
    }

    def behind() -> list[tuple[int, str, int]]:
        short = []
        for n, client in enumerate(clients):
            for topic in TOPICS:
                got = len(client.stamps[topic]) - bisect.bisect_right(
                    client.stamps[topic], newest[topic]
                )
                if got < count:
                    short.append((n, topic, got))
        return short

    await eventually(
        f"every healthy client to receive {count} messages on each topic {what}",
        lambda: not behind(),
        120 * SECOND,
        detail=lambda: f"(client, topic, received) still short: {behind()[:10]}",
    )
    return newest


def delivered_alike(clients: list[Healthy], since: dict[str, int]) -> dict[str, int]:
    """Check that each client got each topic's messages in order (their stamps rising),
    and, of those newer than ``since``, the same ones as every other client up to the
    newest all of them have; how many those are, by topic."""
    span = {}
    for topic in TOPICS:
        for n, client in enumerate(clients):
            stamps = client.stamps[topic]
            assert all(a < b for a, b in itertools.pairwise(stamps)), (topic, n, stamps)
        seen = [[t for t in c.stamps[topic] if t > since[topic]] for c in clients]
        last = min(s[-1] for s in seen)
        common = [[t for t in s if t <= last] for s in seen]
        for n, stamps in enumerate(common):
            assert stamps == common[0], (topic, n, sorted(set(stamps) ^ set(common[0]))[:10])
        span[topic] = len(common[0])
    return span


async def subscribers(client: Healthy, expected: int) -> None:
    """Wait until the camera has ``expected`` subscribers, as the lab's rosapi says."""
    deadline = time.monotonic() + 60 * SECOND
    while True:
        answer = await client.call("/rosapi/subscribers", {"topic": CAMERA})
        count = len(answer["values"]["subscribers"])  # type: ignore[index]
        if count == expected:
            return
        assert time.monotonic() < deadline, f"{count} subscribers to the camera, not {expected}"
        await asyncio.sleep(0.05)  # a poll of the lab's own count, not a wait for time


@pytest.mark.timeout(300 * SECOND)
def test_200_clients_half_never_reading(served):
    """With 100 stalled camera subscribers beside them, each of 100 healthy clients goes
    on receiving the camera and odometry, in order and missing nothing another healthy
    client got; the server's memory stays bounded, client 201 is refused, and the
    stalled clients' subscriptions are released when they leave."""
    # every client comes from 127.0.0.1: no share per address, the bridge's limit alone
    lab = served(
        "--robot", "icreate-1=icreate-maze", "--no-playground", "--workers", "0",
        "--max-connections-per-address", "0",
        "--param", "time_limit=3600",  # one episode: its stamps only rise
    ).start()  # fmt: skip
    path = "/robots/icreate-1"
    port = int(lab.bridge.rsplit(":", 1)[1])
    figures = asyncio.run(crowd(lab, lab.bridge + path, port, path))
    print(
        "crowd:", {k: v for k, v in figures.items() if k.startswith(("span", "refused"))},
        f"RSS {figures['rss_before'] / 1e6:.0f} MB -> peak {figures['rss_peak'] / 1e6:.0f} MB",
    )  # fmt: skip
    for topic in TOPICS:  # the same messages reached every client, this many of them
        assert figures["span_alone"][topic] >= MESSAGES, figures
        assert figures["span_beside_stalled"][topic] >= MESSAGES, figures
    assert figures["rss_peak"] - figures["rss_before"] < GROWTH, figures
    assert figures["refused_status"] == 503
    assert lab.process.poll() is None, lab.log


async def crowd(lab, url: str, port: int, path: str) -> dict[str, object]:
    healthy = [Healthy(await connect(url, max_size=None, compression=None)) for _ in range(HEALTHY)]
    try:
        for client in healthy:
            await client.subscribe()
        newest = await each_receives(healthy, MESSAGES, "alone")
        span_alone = delivered_alike(healthy, newest)
        rss_before = lab.rss()
        sampler = Sampler(lab)
        stalled = await asyncio.gather(
            *(asyncio.to_thread(stalled_client, port, path) for _ in range(STALLED))
        )
        try:
            await subscribers(healthy[0], HEALTHY + STALLED)  # every stalled client's is in
            newest = await each_receives(healthy, MESSAGES, "beside the stalled clients")
            span_beside = delivered_alike(healthy, newest)
            try:
                async with connect(url, open_timeout=10 * SECOND):
                    refused = 101
            except InvalidStatus as err:
                refused = err.response.status_code
            rss_peak = sampler.close()
        finally:
            for sock in stalled:
                sock.close()
        await subscribers(healthy[0], HEALTHY)  # the stalled clients' go as they leave
        return {
            "span_alone": span_alone,
            "span_beside_stalled": span_beside,
            "rss_before": rss_before,
            "rss_peak": rss_peak,
            "refused_status": refused,
        }
    finally:
        for client in healthy:
            await client.ws.close()
            client.reader.cancel()
