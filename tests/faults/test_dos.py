"""Denial of service from anonymous clients: the lab stays open to everyone else.

Each test attacks a real `labd serve` on loopback with real clients. Loopback has more
than one address (all of 127.0.0.0/8), so an attacker on 127.0.0.1 and a bystander on
127.0.0.2 are two addresses to the lab, as two machines would be:

- one address opens bridge connections until it is refused: it gets its share
  (32, the default) and a 503 saying so, and another address is still let in;
- slowloris, on a machine whose open-file limit is 1,024 (the usual default): a
  thousand connections that send a header byte every second, to the HTTP port and the
  bridge. Another address still gets a page and a bridge connection at once, the
  slow connections are cut at the header timeout, and the log stays small;
- 100 anonymous readers of the pages and of a live robot's 3D scene, through resets:
  the robot's `/clock` keeps its rate;
- the same export asked for again, and by several clients at once: built once;
- a 1 GiB blob uploaded by a worker: the live robot's camera and clock never stall.
"""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import itertools
import resource
import socket
import statistics
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import orjson
import psutil
import pytest
from websockets.asyncio.client import ClientConnection, connect
from websockets.exceptions import InvalidStatus

from labd.config import BridgeConfig, HttpConfig
from scheduler.remote import PROTOCOL, PROTOCOL_HEADER
from tests.faults.conftest import wait_for

pytestmark = [pytest.mark.integration, pytest.mark.rates]

ATTACKER, BYSTANDER = "127.0.0.1", "127.0.0.2"  # two addresses of loopback
SHARE = BridgeConfig().max_connections_per_address
HTTP = HttpConfig()
KEPT = 0.85  # share of its rate alone a live robot keeps under attack
CLOCK = ("/clock", "rosgraph_msgs/msg/Clock")
CAMERA = ("/camera/image/compressed", "sensor_msgs/msg/CompressedImage")


def port_of(url: str) -> int:
    return int(url.split("/")[2].rsplit(":", 1)[1])


async def bridge_client(url: str, address: str = ATTACKER, **kwargs: Any) -> ClientConnection:
    """A WebSocket client of the bridge, connecting from ``address``."""
    kwargs.setdefault("open_timeout", 10)
    return await connect(url, local_addr=(address, 0), **kwargs)


class Watcher:
    """A bridge client that subscribes to topics and notes when each message arrives."""

    def __init__(self, ws: ClientConnection, topics: tuple[tuple[str, str], ...]) -> None:
        self.ws = ws
        self.topics = topics
        self.arrivals: dict[str, list[float]] = {topic: [] for topic, _ in topics}
        self.replies: asyncio.Queue[dict[str, Any]] = asyncio.Queue()
        self.reader = asyncio.create_task(self._read())

    @classmethod
    async def open(cls, url: str, *topics: tuple[str, str]) -> Watcher:
        watcher = cls(await bridge_client(url, BYSTANDER, max_size=None), topics)
        for topic, type_name in topics:
            frame = {"op": "subscribe", "topic": topic, "type": type_name}
            await watcher.ws.send(orjson.dumps(frame).decode())
        return watcher

    async def _read(self) -> None:
        async for frame in self.ws:
            message = orjson.loads(frame)
            if message["op"] == "publish":
                self.arrivals[message["topic"]].append(time.monotonic())
            else:
                await self.replies.put(message)

    async def call(self, service: str) -> dict[str, Any]:
        frame = {"op": "call_service", "service": service, "args": {}, "id": service}
        await self.ws.send(orjson.dumps(frame).decode())
        return await asyncio.wait_for(self.replies.get(), 30)

    def rate(self, topic: str, start: float, end: float) -> float:
        """Messages per second on ``topic`` that arrived from ``start`` to ``end``."""
        return sum(start <= t < end for t in self.arrivals[topic]) / (end - start)

    def longest_gap(self, topic: str, start: float, end: float) -> float:
        """The longest time from ``start`` to ``end`` with no message on ``topic``."""
        times = [start, *(t for t in self.arrivals[topic] if start <= t < end), end]
        return max(b - a for a, b in itertools.pairwise(times))

    async def close(self) -> None:
        await self.ws.close()
        self.reader.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await self.reader


async def window(seconds: float) -> tuple[float, float]:
    """A measurement window of ``seconds``, from now: its start and end."""
    start = time.monotonic()
    await asyncio.sleep(seconds)  # a measurement window, not a wait for a condition
    return start, time.monotonic()


# -- 1. one address takes every bridge slot ---------------------------------------------------


@pytest.mark.timeout(120)
def test_one_address_gets_only_its_share_of_the_bridge(served):
    """An address that opens bridge connections until refused gets its share (32 by
    default) and a 503 that says so; another address is still let in, and a slot freed
    by the first address is its own again."""
    lab = served("--robot", "icreate-1=icreate-maze", "--no-playground", "--no-service").start()
    url = lab.bridge + "/robots/icreate-1"
    figures = asyncio.run(take_every_slot(url, BridgeConfig().max_connections))
    print("bridge slots:", {k: v for k, v in figures.items() if k != "reason"})
    assert figures["attacker_admitted"] == SHARE == 32, figures
    assert figures["attacker_refused"] == 503, figures
    assert f"{SHARE} connections from your address" in figures["reason"], figures
    assert figures["bystander"] == 101, figures
    assert figures["attacker_after_leaving"] == 101, figures
    assert lab.process.poll() is None, lab.log


async def take_every_slot(url: str, limit: int) -> dict[str, Any]:
    held: list[ClientConnection] = []
    figures: dict[str, Any] = {"attacker_refused": None, "reason": ""}
    try:
        for _ in range(limit + 1):  # every slot the bridge has, and one more
            try:
                held.append(await bridge_client(url))
            except InvalidStatus as err:
                figures["attacker_refused"] = err.response.status_code
                figures["reason"] = err.response.body.decode(errors="replace")
                break
        figures["attacker_admitted"] = len(held)
        figures["bystander"] = await status_of(url, BYSTANDER)
        await held.pop().close()
        figures["attacker_after_leaving"] = await status_of(url, ATTACKER)
    finally:
        for ws in held:
            await ws.close()
    return figures


async def status_of(url: str, address: str) -> int:
    """101 if a client from ``address`` is let in, else the status it is refused with."""
    try:
        async with await bridge_client(url, address):
            return 101
    except InvalidStatus as err:
        return err.response.status_code


# -- 2. slowloris -----------------------------------------------------------------------------

SLOW = 1_100  # connections: past the usual limit of 1,024 open files
SLOW_FOR = 12.0  # seconds the slow clients keep at it
HEADER_TIMEOUT = 3.0  # the lab's header timeout in this test (default 10 s)
LOG_BYTES = 64 * 1024  # the whole log of the lab under attack, at most


@contextlib.contextmanager
def open_files_limit(soft: int) -> Iterator[None]:
    """Processes started meanwhile inherit a soft limit of ``soft`` open files."""
    was = resource.getrlimit(resource.RLIMIT_NOFILE)
    resource.setrlimit(resource.RLIMIT_NOFILE, (min(soft, was[1]), was[1]))
    try:
        yield
    finally:
        resource.setrlimit(resource.RLIMIT_NOFILE, was)


@pytest.mark.timeout(180)
def test_slowloris_locks_out_nobody(served):
    """1,100 connections from one address sending a header byte a second (more than a
    1,024-file limit holds), each coming back when cut: another address gets the home
    page and a bridge connection within 2 s (the median of three tries), each slow
    connection is cut at the header timeout or refused, the address never holds more
    than 256 HTTP connections and 32 bridge handshakes, and the lab's log stays under
    64 KiB."""
    lab = served(
        "--robot", "icreate-1=icreate-maze", "--no-playground", "--workers", "0",
        "--header-timeout", str(HEADER_TIMEOUT),
    )  # fmt: skip
    with open_files_limit(1024):
        lab.start()
    started_log = len(lab.log.encode())
    figures = asyncio.run(slowloris(lab.server, lab.bridge + "/robots/icreate-1", lab.pid))
    log_bytes = len(lab.log.encode()) - started_log
    print("slowloris:", figures, f"log {log_bytes} bytes")
    assert statistics.median(figures["page_seconds"]) < 2.0, figures
    assert statistics.median(figures["bridge_seconds"]) < 2.0, figures
    assert figures["longest_held"] < HEADER_TIMEOUT + 2.0, figures
    assert 0 < figures["most_held_http"] <= HTTP.max_connections_per_address == 256, figures
    assert 0 < figures["most_held_bridge"] <= SHARE, figures  # in their handshake
    assert log_bytes < LOG_BYTES, lab.log[-4000:]
    assert lab.process.poll() is None, lab.log[-4000:]


async def slowloris(server: str, bridge: str, pid: int) -> dict[str, Any]:
    stop = asyncio.Event()
    held: list[float] = []  # how long each slow connection was kept before it was cut
    ports = (port_of(server), port_of(bridge))
    slow = [asyncio.create_task(slow_client(ports[i % 2], stop, held)) for i in range(SLOW)]
    most = dict.fromkeys(ports, 0)

    async def count() -> None:
        """The attacker's connections the lab held across two looks 0.5 s apart (not
        those it was refusing just then), most at once on each port."""
        before: dict[int, set[int]] = {port: set() for port in ports}
        while not stop.is_set():
            await asyncio.sleep(0.5)
            conns = await asyncio.to_thread(psutil.Process(pid).net_connections, "tcp")
            for port in ports:
                now = {
                    c.raddr.port
                    for c in conns
                    if c.laddr.port == port and c.raddr and c.raddr.ip == ATTACKER
                }
                most[port] = max(most[port], len(now & before[port]))
                before[port] = now

    counting = asyncio.create_task(count())
    pages: list[float] = []
    bridges: list[float] = []
    try:
        await asyncio.sleep(SLOW_FOR / 4)  # the attack in full swing
        transport = httpx.AsyncHTTPTransport(local_address=BYSTANDER)
        async with httpx.AsyncClient(transport=transport, timeout=30) as client:
            for _ in range(3):  # a bystander comes three times during the attack
                began = time.monotonic()
                page = await client.get(server + "/", headers={"Connection": "close"})
                pages.append(time.monotonic() - began)
                assert page.status_code == 200, page.text
                began = time.monotonic()
                async with await bridge_client(bridge, BYSTANDER, open_timeout=30):
                    bridges.append(time.monotonic() - began)
                await asyncio.sleep(SLOW_FOR / 4)
    finally:
        stop.set()
        await asyncio.gather(*slow, counting)
    return {
        "page_seconds": [round(t, 2) for t in pages],
        "most_held_http": most[ports[0]],
        "most_held_bridge": most[ports[1]],
        "bridge_seconds": [round(t, 2) for t in bridges],
        "connections": len(held),
        "cut_or_refused": sum(h < SLOW_FOR for h in held),
        "longest_held": round(max(held), 2),
        "median_held": round(statistics.median(held), 2),
    }


async def slow_client(port: int, stop: asyncio.Event, held: list[float]) -> None:
    """Open connections one after another, each sending a request head a byte a second
    and never finishing it, until ``stop``; note how long each one was kept."""
    while not stop.is_set():
        began = time.monotonic()
        try:
            reader, writer = await asyncio.open_connection(ATTACKER, port)
        except OSError:
            await asyncio.sleep(1.0)
            continue
        try:
            writer.write(b"GET / HTTP/1.1\r\nHost: lab\r\n")
            while not stop.is_set() and not reader.at_eof():
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(reader.read(4096), 1.0)  # sees the cut at once
                writer.write(b"X")
                await writer.drain()
        except OSError:
            pass
        finally:
            held.append(time.monotonic() - began)
            writer.close()
        await asyncio.sleep(2.0)  # then it comes back


BAD = 2_000  # requests that are not HTTP


@pytest.mark.timeout(120)
def test_a_flood_of_bad_requests_is_logged_a_few_times_a_second(served):
    """2,000 requests that are not HTTP, one after another: each is answered 400, and
    the lab's log grows by under 4 KiB (the warning a few times a second, then how
    many like it were held back)."""
    lab = served("--no-robots", "--workers", "0").start()
    started_log = len(lab.log.encode())
    port = port_of(lab.server)
    began = time.monotonic()
    for _ in range(BAD):
        with socket.create_connection((ATTACKER, port)) as sock:
            sock.sendall(b"BAD\x00 / HTTP/1.1\r\n\r\n")
            assert sock.recv(64).startswith(b"HTTP/1.1 400 ")
    seconds = time.monotonic() - began
    wait_for("the log to say how many it held back", lambda: "more like it" in lab.log, 10)
    log_bytes = len(lab.log.encode()) - started_log
    print(f"bad requests: {BAD} in {seconds:.1f} s, log {log_bytes} bytes")
    assert log_bytes < 4096, lab.log[-4000:]


# -- 3. readers of pages and the scene --------------------------------------------------------

READERS = 100
SCENE = "/api/robots/pr2-1/scene"
PAGES = (SCENE, "/", SCENE, "/robots/pr2-1", SCENE, "/trials", SCENE, "/robots")


@pytest.mark.timeout(180)
def test_readers_of_pages_and_the_scene_do_not_slow_the_robot(served):
    """100 anonymous readers of the pages and of the PR2's 3D scene (half of them the
    scene), while the robot's episode is reset three times: its /clock, as a WebSocket
    client sees it, keeps at least 85 % of its rate alone."""
    lab = served("--robot", "pr2-1=pr2-table", "--no-playground", "--workers", "0").start()
    figures = asyncio.run(readers(lab.server, lab.bridge + "/robots/pr2-1"))
    print("readers:", figures)
    assert figures["alone"] > 10, figures  # the robot really runs
    assert figures["requests"] > READERS, figures  # the readers really read
    assert figures["beside_readers"] >= KEPT * figures["alone"], figures
    assert figures["failed"] == [], figures
    assert lab.process.poll() is None, lab.log[-4000:]


async def readers(server: str, bridge: str) -> dict[str, Any]:
    watcher = await Watcher.open(bridge, CLOCK)
    try:
        await asyncio.sleep(2.0)  # warm-up: the robot steps once someone listens
        start, end = await window(6.0)
        alone = watcher.rate("/clock", start, end)
        stop = asyncio.Event()
        latencies: list[tuple[float, float]] = []  # when each request began, how long it took
        failed: list[str] = []
        limits = httpx.Limits(max_connections=READERS, max_keepalive_connections=READERS)
        async with httpx.AsyncClient(base_url=server, limits=limits, timeout=120) as client:
            tasks = [
                asyncio.create_task(reader(client, PAGES[n % len(PAGES)], stop, latencies, failed))
                for n in range(READERS)
            ]
            await asyncio.sleep(2.0)  # every reader at it
            start = time.monotonic()
            for _ in range(3):  # a new episode: a new scene to describe
                answer = await watcher.call("/lab/reset")
                assert answer["values"]["success"], answer
                await asyncio.sleep(3.0)  # a measurement window, not a wait for a condition
            end = time.monotonic()
            stop.set()
            await asyncio.gather(*tasks)
        timed = sorted(took for began, took in latencies if start <= began < end)
        return {
            "alone": round(alone, 2),
            "beside_readers": round(watcher.rate("/clock", start, end), 2),
            "longest_gap": round(watcher.longest_gap("/clock", start, end), 3),
            "requests": len(timed),  # begun in the window, as the two below
            "p50": round(timed[len(timed) // 2], 3),
            "p99": round(timed[int(len(timed) * 0.99)], 3),
            "failed": failed[:5],
        }
    finally:
        await watcher.close()


async def reader(
    client: httpx.AsyncClient,
    path: str,
    stop: asyncio.Event,
    latencies: list[tuple[float, float]],
    failed: list[str],
) -> None:
    """Read ``path`` again and again until ``stop``; note each answer's time, and what
    failed (a status other than 200, a connection dropped)."""
    while not stop.is_set():
        began = time.monotonic()
        try:
            answer = await client.get(path)
        except httpx.TransportError as err:
            failed.append(f"{path}: {err!r}")
            continue
        if answer.status_code != 200:
            failed.append(f"{path}: {answer.status_code} {answer.text[:200]}")
        latencies.append((began, time.monotonic() - began))


# -- 4. exports -------------------------------------------------------------------------------


@pytest.mark.timeout(300)
def test_an_export_is_built_once(served, tmp_path: Path):
    """The same export asked for again is served without being built again (under a
    quarter of the first request's time), and four clients asking at once for a new one
    share one build (under twice one build's time), all getting the same bytes."""
    data = tmp_path / "data"
    lab = served("--no-robots", "--workers", "0", data=data)
    filed = lab.labd("demonstrate", "--data", str(data), "--count", "2", "--json")
    assert filed.returncode == 0, filed.stderr
    lab.start()
    ids = [t["id"] for t in lab.get("/api/trials?kind=demonstration")["trials"]]
    assert len(ids) == 2, ids
    figures = asyncio.run(export_requests(lab.server, ids))
    print("exports:", {k: v for k, v in figures.items() if k != "digests"})
    assert figures["again"] < 0.25 * figures["first"], figures
    assert figures["four_at_once"] < 2.0 * figures["single_first"], figures
    assert figures["single_again"] < 0.25 * figures["single_first"], figures
    assert len(set(figures["digests"])) == 2, figures  # one dataset each, the same every time
    assert lab.process.poll() is None, lab.log[-4000:]


async def export_requests(server: str, ids: list[int]) -> dict[str, Any]:
    async with httpx.AsyncClient(base_url=server, timeout=240) as client:

        async def get(path: str, **params: Any) -> tuple[float, str]:
            began = time.monotonic()
            answer = await client.get(path, params=params)
            assert answer.status_code == 200, answer.text
            return time.monotonic() - began, hashlib.sha256(answer.content).hexdigest()

        first, made = await get("/api/exports/parquet", trials=ids)
        again, again_made = await get("/api/exports/parquet", trials=ids)
        single = f"/api/trials/{ids[0]}/export/lerobot"
        four = await asyncio.gather(*(get(single) for _ in range(4)))
        four_at_once = max(seconds for seconds, _ in four)
        single_again, single_made = await get(single)
        # one build of the single-trial export alone, for scale: the other trial's
        single_first, _ = await get(f"/api/trials/{ids[1]}/export/lerobot")
    return {
        "first": round(first, 2),
        "again": round(again, 2),
        "four_at_once": round(four_at_once, 2),
        "single_again": round(single_again, 2),
        "single_first": round(single_first, 2),
        "digests": [made, again_made] + [d for _, d in four] + [single_made],
    }


# -- 5. a large upload ------------------------------------------------------------------------

UPLOAD = 1 << 30  # bytes a worker uploads
BLOCK = 1 << 20
GAP = 1.5  # seconds the robot's camera or clock may go without a message (30 periods; 3.3 s before)


def upload_blocks() -> Iterator[bytes]:
    block = hashlib.sha256(b"labd").digest() * (BLOCK // 32)
    for n in range(UPLOAD // BLOCK):
        yield n.to_bytes(8, "big") + block[8:]


@pytest.mark.timeout(300)
def test_a_large_upload_does_not_stall_the_robot(served):
    """A worker uploads a 1 GiB blob: meanwhile a live robot's camera and clock, as a
    WebSocket client sees them, never go 1 s without a message, and the blob is stored."""
    lab = served("--robot", "icreate-1=icreate-maze", "--no-playground", "--workers", "0")
    lab.token = lab.add_user("worker", "--worker")
    lab.start()
    sha = hashlib.sha256()
    for block in upload_blocks():
        sha.update(block)
    digest = f"sha256:{sha.hexdigest()}"
    figures = asyncio.run(upload(lab, digest))
    print("upload:", figures)
    assert figures["status"] == 201, figures
    assert figures["camera_alone"] > 5, figures  # the camera really renders
    assert figures["clock_gap"] < GAP and figures["camera_gap"] < GAP, figures
    assert lab.process.poll() is None, lab.log[-4000:]
    lab.stop()
    for blob in lab.data.rglob(digest.removeprefix("sha256:") + "*"):
        blob.unlink()  # 1 GiB: a run's folders stay small on a small disk


async def upload(lab: Any, digest: str) -> dict[str, Any]:
    watcher = await Watcher.open(lab.bridge + "/robots/icreate-1", CLOCK, CAMERA)
    try:
        await asyncio.sleep(2.0)  # warm-up: the camera renders for its first watcher
        start, end = await window(4.0)
        camera_alone = watcher.rate(CAMERA[0], start, end)

        headers = {"Authorization": f"Bearer {lab.token}", PROTOCOL_HEADER: str(PROTOCOL)}
        start = time.monotonic()
        # on a thread: this loop only reads the robot's messages, and notes them on time
        answer = await asyncio.to_thread(
            httpx.put,
            f"{lab.server}/api/blobs/{digest}",
            content=upload_blocks(),
            headers=headers,
            timeout=240,
        )
        end = time.monotonic()
        await asyncio.sleep(1.0)  # the robot's messages of the last moment arrive
        return {
            "status": answer.status_code,
            "seconds": round(end - start, 2),
            "camera_alone": round(camera_alone, 2),
            "clock_gap": round(watcher.longest_gap(CLOCK[0], start, end), 3),
            "camera_gap": round(watcher.longest_gap(CAMERA[0], start, end), 3),
            "camera_during": round(watcher.rate(CAMERA[0], start, end), 2),
        }
    finally:
        await watcher.close()
