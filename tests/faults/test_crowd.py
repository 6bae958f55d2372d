"""A crowd on a live robot: 200 WebSocket clients at once, half of them never reading.

`labd serve` hosts one live robot (``/robots/icreate-1``, its camera at 20 frames a
second while anyone watches). A hundred healthy clients subscribe to its camera and
odometry and read everything; their message rates are measured alone, then again
while a hundred more clients subscribe to the camera and never read a byte. The
healthy ones must keep their rate, the server's memory must stay bounded, and the
connection limit (200, the default) must turn away the 201st client with a 503.
"""

from __future__ import annotations

import asyncio
import socket
import threading
import time

import orjson
import pytest
from websockets.asyncio.client import ClientConnection, connect
from websockets.exceptions import InvalidStatus

pytestmark = [pytest.mark.integration, pytest.mark.rates]

HEALTHY = 100
STALLED = 100
WINDOW = 4.0  # seconds each rate is measured over (80 messages at 20 Hz)
KEPT = 0.85  # share of its rate alone a healthy client keeps beside the stalled ones
GROWTH = 150 * 1024 * 1024  # bytes the server may grow by with the stalled clients
CAMERA = "/camera/image/compressed"
TOPICS = {CAMERA: "sensor_msgs/msg/CompressedImage", "/odom": "nav_msgs/msg/Odometry"}


class Healthy:
    """A client that subscribes to the camera and odometry and reads all it is sent."""

    def __init__(self, ws: ClientConnection) -> None:
        self.ws = ws
        self.counts = dict.fromkeys(TOPICS, 0)
        self.replies: asyncio.Queue[dict[str, object]] = asyncio.Queue()
        self.reader = asyncio.create_task(self._read())

    async def _read(self) -> None:
        async for frame in self.ws:
            message = orjson.loads(frame)
            if message["op"] == "publish":
                self.counts[message["topic"]] += 1
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
        return await asyncio.wait_for(self.replies.get(), 30)


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


async def rates(clients: list[Healthy], seconds: float) -> dict[str, list[float]]:
    """Messages per second each client received on each topic over ``seconds``."""
    before = [dict(c.counts) for c in clients]
    await asyncio.sleep(seconds)  # a measurement window, not a wait for a condition
    return {
        topic: [
            (c.counts[topic] - b[topic]) / seconds for c, b in zip(clients, before, strict=True)
        ]
        for topic in TOPICS
    }


def mean(values: list[float]) -> float:
    return sum(values) / len(values)


@pytest.mark.timeout(240)
def test_200_clients_half_never_reading(served):
    """With 100 stalled camera subscribers beside them, 100 healthy clients keep their camera
    and odometry rates, the server's memory stays bounded, client 201 is refused, and the
    stalled clients' subscriptions are released when they leave."""
    # every client comes from 127.0.0.1: no share per address, the bridge's limit alone
    lab = served(
        "--robot", "icreate-1=icreate-maze", "--no-playground", "--workers", "0",
        "--max-connections-per-address", "0",
    ).start()  # fmt: skip
    path = "/robots/icreate-1"
    port = int(lab.bridge.rsplit(":", 1)[1])
    figures = asyncio.run(crowd(lab, lab.bridge + path, port, path))
    alone, beside = figures["alone"], figures["beside_stalled"]
    print(
        "crowd:",
        {t: (round(mean(alone[t]), 2), round(mean(beside[t]), 2), min(beside[t])) for t in TOPICS},
        f"RSS {figures['rss_before'] / 1e6:.0f} MB -> peak {figures['rss_peak'] / 1e6:.0f} MB",
    )
    for topic in TOPICS:
        assert mean(alone[topic]) > 5, (topic, alone[topic])  # the robot really publishes
        assert mean(beside[topic]) >= KEPT * mean(alone[topic]), (topic, figures)
        assert min(beside[topic]) >= KEPT * mean(alone[topic]) * 0.8, (topic, figures)
    assert figures["rss_peak"] - figures["rss_before"] < GROWTH, figures
    assert figures["refused_status"] == 503
    assert lab.process.poll() is None, lab.log


async def crowd(lab, url: str, port: int, path: str) -> dict[str, object]:
    healthy = [Healthy(await connect(url, max_size=None, compression=None)) for _ in range(HEALTHY)]
    try:
        for client in healthy:
            await client.subscribe()
        await asyncio.sleep(1.0)  # warm-up: the camera starts rendering for its first watcher
        alone = await rates(healthy, WINDOW)
        rss_before = lab.rss()
        sampler = Sampler(lab)
        stalled = await asyncio.gather(
            *(asyncio.to_thread(stalled_client, port, path) for _ in range(STALLED))
        )
        try:
            deadline = time.monotonic() + 30
            while True:  # every stalled client's subscription is in the graph
                answer = await healthy[0].call("/rosapi/subscribers", {"topic": CAMERA})
                if len(answer["values"]["subscribers"]) >= HEALTHY + STALLED:
                    break
                assert time.monotonic() < deadline, answer
                await asyncio.sleep(0.05)
            beside = await rates(healthy, WINDOW)
            try:
                async with connect(url, open_timeout=10):
                    refused = 101
            except InvalidStatus as err:
                refused = err.response.status_code
            rss_peak = sampler.close()
        finally:
            for sock in stalled:
                sock.close()
        deadline = time.monotonic() + 30
        while True:  # the stalled clients' subscriptions are released as they leave
            answer = await healthy[0].call("/rosapi/subscribers", {"topic": CAMERA})
            if len(answer["values"]["subscribers"]) == HEALTHY:
                break
            assert time.monotonic() < deadline, answer
            await asyncio.sleep(0.05)
        return {
            "alone": alone,
            "beside_stalled": beside,
            "rss_before": rss_before,
            "rss_peak": rss_peak,
            "refused_status": refused,
            "camera_alone": mean(alone[CAMERA]),
            "camera_beside": mean(beside[CAMERA]),
        }
    finally:
        for client in healthy:
            await client.ws.close()
            client.reader.cancel()
