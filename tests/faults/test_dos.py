"""Denial of service from anonymous clients: the lab stays open to everyone else.

Each test attacks a real `labd serve` on loopback with real clients. Loopback has more
than one address (all of 127.0.0.0/8), so an attacker on 127.0.0.1 and a bystander on
127.0.0.2 are two addresses to the lab, as two machines would be:

- one address opens bridge connections until it is refused: it gets its share
  (32, the default) and a 503 saying so, and another address is still let in;
- slowloris, on a machine whose open-file limit is 1,024 (the usual default): a
  thousand connections that send a header byte every second, to the HTTP port and the
  bridge. Another address still gets a page and a bridge connection, every slow
  connection is cut by the lab (at the header timeout, never before) or refused, and
  the log stays small;
- 100 anonymous readers of the pages and of a live robot's 3D scene, through resets:
  the robot's `/clock` goes on after each reset, in order, and every reader is answered;
- the same export asked for again, and by several clients at once: built once;
- a 1 GiB blob uploaded by a worker: the live robot's camera and clock go on while the
  upload is under way.

The tests assert what the lab does, never how fast: how long the bystander waits, the
robot's rates beside the readers and the gaps during the upload are measured by
``bench/crowds.py``, each against the same figure without the attack.
"""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import itertools
import re
import resource
import socket
import statistics
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import orjson
import psutil
import pytest
from websockets.asyncio.client import ClientConnection, connect
from websockets.exceptions import InvalidStatus

from labd.config import BridgeConfig, HttpConfig
from labd.logs import BURST, RATE
from scheduler.remote import PROTOCOL, PROTOCOL_HEADER
from tests.faults.conftest import wait_for
from tests.helpers.timing import SECOND, eventually

pytestmark = [pytest.mark.integration, pytest.mark.rates]

ATTACKER, BYSTANDER = "127.0.0.1", "127.0.0.2"  # two addresses of loopback
SHARE = BridgeConfig().max_connections_per_address
HTTP = HttpConfig()
CLOCK = ("/clock", "rosgraph_msgs/msg/Clock")
CAMERA = ("/camera/image/compressed", "sensor_msgs/msg/CompressedImage")


def port_of(url: str) -> int:
    return int(url.split("/")[2].rsplit(":", 1)[1])


async def bridge_client(url: str, address: str = ATTACKER, **kwargs: Any) -> ClientConnection:
    """A WebSocket client of the bridge, connecting from ``address``."""
    kwargs.setdefault("open_timeout", 30 * SECOND)
    return await connect(url, local_addr=(address, 0), **kwargs)


class Watcher:
    """A bridge client that subscribes to topics and notes when each message arrives."""

    def __init__(self, ws: ClientConnection, topics: tuple[tuple[str, str], ...]) -> None:
        self.ws = ws
        self.topics = topics
        self.arrivals: dict[str, list[float]] = {topic: [] for topic, _ in topics}
        self.stamps: dict[str, list[int]] = {topic: [] for topic, _ in topics}  # sim time, ns
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
                msg = message["msg"]
                stamp = msg["clock"] if "clock" in msg else msg["header"]["stamp"]
                self.stamps[message["topic"]].append(stamp["sec"] * 10**9 + stamp["nanosec"])
            else:
                await self.replies.put(message)

    async def call(self, service: str) -> dict[str, Any]:
        frame = {"op": "call_service", "service": service, "args": {}, "id": service}
        await self.ws.send(orjson.dumps(frame).decode())
        return await asyncio.wait_for(self.replies.get(), 30 * SECOND)

    async def hears(self, count: int, *topics: str) -> None:
        """Wait until ``count`` more messages have come on each of ``topics``."""
        marks = {topic: len(self.arrivals[topic]) for topic in topics}
        await eventually(
            f"{count} more messages on {', '.join(topics)}",
            lambda: all(len(self.arrivals[t]) - marks[t] >= count for t in topics),
            60 * SECOND,
            detail=lambda: {t: len(self.arrivals[t]) - marks[t] for t in topics},
        )

    async def close(self) -> None:
        await self.ws.close()
        self.reader.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await self.reader


# -- 1. one address takes every bridge slot ---------------------------------------------------


@pytest.mark.timeout(120 * SECOND)
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
HEADER_TIMEOUT = 3.0  # the lab's header timeout in this test (default 10 s)
LET_GO = 60 * SECOND  # after the attack, a slow connection the lab has not cut is kept
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


@pytest.mark.timeout(240 * SECOND)
def test_slowloris_locks_out_nobody(served):
    """1,100 connections from one address sending a header byte a second (more than a
    1,024-file limit holds), each coming back when cut: another address gets the home
    page and a bridge connection three times during the attack, every slow connection is
    refused or cut by the lab (an HTTP one answered 408 at the header timeout, never
    before), the address never holds more than 256 HTTP connections and 32 bridge
    handshakes, and the lab's log stays under 64 KiB."""
    lab = served(
        "--robot", "icreate-1=icreate-maze", "--no-playground", "--workers", "0",
        "--header-timeout", str(HEADER_TIMEOUT),
    )  # fmt: skip
    with open_files_limit(1024):
        lab.start()
    started_log = len(lab.log.encode())
    figures = asyncio.run(slowloris(lab.server, lab.bridge + "/robots/icreate-1", lab.pid))
    log_bytes = len(lab.log.encode()) - started_log
    ended: list[Ended] = figures.pop("ended")
    timed_out = [e for e in ended if e.answer.startswith(b"HTTP/1.1 408 ")]
    figures |= {
        "connections": len(ended),
        "answers": {a: sum(e.answer[:12] == a for e in ended) for a in {e.answer[:12] for e in ended}},
        "shortest_408": round(min(e.seconds for e in timed_out), 2),
        "longest_held": round(max(e.seconds for e in ended), 2),
    }  # fmt: skip
    print("slowloris:", figures, f"log {log_bytes} bytes")
    assert len(figures["page_seconds"]) == len(figures["bridge_seconds"]) == 3, figures
    kept = [e for e in ended if not e.by_lab]
    assert not kept, f"{len(kept)} slow connections were never cut by the lab: {figures}"
    assert timed_out and all(e.seconds >= HEADER_TIMEOUT for e in timed_out), figures
    assert 0 < figures["most_held_http"] <= HTTP.max_connections_per_address == 256, figures
    assert 0 < figures["most_held_bridge"] <= SHARE, figures  # in their handshake
    assert log_bytes < LOG_BYTES, lab.log[-4000:]
    assert lab.process.poll() is None, lab.log[-4000:]


@dataclass
class Ended:
    """A slow connection, once over: how long it was kept, the first bytes the lab
    answered (none when it just closed it), and whether the lab ended it (else the test
    let go of it, ``LET_GO`` after the attack)."""

    seconds: float
    answer: bytes
    by_lab: bool


class Attack:
    """The slow clients' state: ``stop`` ends the attack (no new connection), after which
    a connection the lab has not cut by ``let_go`` is given up."""

    def __init__(self) -> None:
        self.stop = asyncio.Event()
        self.let_go = float("inf")
        self.ended: list[Ended] = []

    def end(self) -> None:
        self.let_go = time.monotonic() + LET_GO
        self.stop.set()


async def slowloris(server: str, bridge: str, pid: int) -> dict[str, Any]:
    attack = Attack()
    ports = (port_of(server), port_of(bridge))
    slow = [asyncio.create_task(slow_client(ports[i % 2], attack)) for i in range(SLOW)]
    most = dict.fromkeys(ports, 0)
    held = dict.fromkeys(ports, 0)

    async def count() -> None:
        """The attacker's connections the lab held across two looks 0.5 s apart (not
        those it was refusing just then), most at once on each port."""
        before: dict[int, set[int]] = {port: set() for port in ports}
        while not attack.stop.is_set():
            await asyncio.sleep(0.5)  # the interval between two looks
            conns = await asyncio.to_thread(psutil.Process(pid).net_connections, "tcp")
            for port in ports:
                now = {
                    c.raddr.port
                    for c in conns
                    if c.laddr.port == port and c.raddr and c.raddr.ip == ATTACKER
                }
                held[port] = len(now & before[port])
                most[port] = max(most[port], held[port])
                before[port] = now

    counting = asyncio.create_task(count())
    pages: list[float] = []
    bridges: list[float] = []
    try:
        await eventually(  # the attack in full swing: the address holds half its shares
            "the attacker to hold half its connections on each port",
            lambda: (
                held[ports[0]] >= HTTP.max_connections_per_address // 2
                and held[ports[1]] >= SHARE // 2
            ),
            60 * SECOND,
            detail=lambda: held,
        )
        transport = httpx.AsyncHTTPTransport(local_address=BYSTANDER)
        async with httpx.AsyncClient(transport=transport, timeout=30 * SECOND) as client:
            for _ in range(3):  # a bystander comes three times during the attack
                began = time.monotonic()
                page = await client.get(server + "/", headers={"Connection": "close"})
                pages.append(time.monotonic() - began)
                assert page.status_code == 200, page.text
                began = time.monotonic()
                async with await bridge_client(bridge, BYSTANDER):
                    bridges.append(time.monotonic() - began)
                cut = len(attack.ended)
                await eventually(  # the attack goes on: connections cut, and back
                    f"{SHARE} more slow connections to end",
                    lambda: len(attack.ended) >= cut + SHARE,  # noqa: B023 (awaited here)
                    60 * SECOND,
                )
    finally:
        attack.end()
        await asyncio.gather(*slow, counting)
    return {
        "page_seconds": [round(t, 2) for t in pages],
        "bridge_seconds": [round(t, 2) for t in bridges],
        "most_held_http": most[ports[0]],
        "most_held_bridge": most[ports[1]],
        "median_held": round(statistics.median(e.seconds for e in attack.ended), 2),
        "ended": attack.ended,
    }


async def slow_client(port: int, attack: Attack) -> None:
    """Open connections one after another, each sending a request head a byte a second
    and never finishing it, until the attack stops; note how each one ended."""
    while not attack.stop.is_set():
        began = time.monotonic()
        try:
            reader, writer = await asyncio.open_connection(ATTACKER, port)
        except OSError:
            await asyncio.sleep(1.0)  # the attacker's pace
            continue
        answer, by_lab = b"", False
        try:
            writer.write(b"GET / HTTP/1.1\r\nHost: lab\r\n")
            while True:
                with contextlib.suppress(TimeoutError):  # a byte a second; sees a cut at once
                    answer += await asyncio.wait_for(reader.read(4096), 1.0)
                if reader.at_eof():
                    by_lab = True
                    break
                if time.monotonic() > attack.let_go:
                    break
                writer.write(b"X")
                await writer.drain()
        except OSError:
            by_lab = True  # reset by the lab
        finally:
            attack.ended.append(Ended(time.monotonic() - began, answer[:64], by_lab))
            writer.close()
        await asyncio.sleep(2.0)  # then it comes back, at the attacker's pace


BAD = 2_000  # requests that are not HTTP


@pytest.mark.timeout(120 * SECOND)
def test_a_flood_of_bad_requests_is_logged_a_few_times_a_second(served):
    """2,000 requests that are not HTTP, one after another: each is answered 400, and
    the lab's log grows by the warning's burst and then a few lines a second at most
    (``labd.logs``: 5, then 2 a second), each saying how many like it were held back,
    with no traceback."""
    lab = served("--no-robots", "--workers", "0").start()
    started_log = len(lab.log.encode())
    port = port_of(lab.server)
    began = time.monotonic()
    for _ in range(BAD):
        with socket.create_connection((ATTACKER, port)) as sock:
            sock.sendall(b"BAD\x00 / HTTP/1.1\r\n\r\n")
            assert sock.recv(64).startswith(b"HTTP/1.1 400 ")
    seconds = time.monotonic() - began
    wait_for("the log to say how many it held back", lambda: "more like it" in lab.log, 10 * SECOND)
    within = time.monotonic() - began  # the log's lines so far came within this time
    logged = lab.log.encode()[started_log:].decode()
    lines = logged.splitlines()
    print(f"bad requests: {BAD} in {seconds:.1f} s, log {len(logged)} bytes, {len(lines)} lines")
    assert len(lines) <= BURST + RATE * within + 1, logged[-4000:]
    assert "Traceback" not in logged and max(map(len, lines)) < 512, logged[-4000:]


# -- 3. readers of pages and the scene --------------------------------------------------------

READERS = 100
SCENE = "/api/robots/pr2-1/scene"
PAGES = (SCENE, "/", SCENE, "/robots/pr2-1", SCENE, "/trials", SCENE, "/robots")


RESET_TICKS = 20  # /clock messages the watcher hears after each reset, readers reading


@pytest.mark.timeout(240 * SECOND)
def test_readers_of_pages_and_the_scene_do_not_slow_the_robot(served):
    """100 anonymous readers of the pages and of the PR2's 3D scene (half of them the
    scene), while the robot's episode is reset three times: after each reset the robot's
    /clock, as a WebSocket client sees it, goes on (20 ticks, in order: it goes back only
    at a reset), every reader is answered again and again, and none fails."""
    lab = served("--robot", "pr2-1=pr2-table", "--no-playground", "--workers", "0").start()
    figures = asyncio.run(readers(lab.server, lab.bridge + "/robots/pr2-1"))
    print("readers:", figures)
    assert figures["clock_in_order"], figures  # rising, or back to 0 at a new episode
    assert figures["clock_back"] <= 3, figures  # back only at the resets
    assert figures["clock_during"] >= 3 * RESET_TICKS, figures
    assert min(figures["answers"]) >= 2, figures  # each reader was answered more than once
    assert figures["failed"] == [], figures
    assert lab.process.poll() is None, lab.log[-4000:]


async def readers(server: str, bridge: str) -> dict[str, Any]:
    watcher = await Watcher.open(bridge, CLOCK)
    try:
        await watcher.hears(RESET_TICKS, CLOCK[0])  # the robot steps once someone listens
        stop = asyncio.Event()
        answers = [0] * READERS  # each reader's answers
        failed: list[str] = []
        limits = httpx.Limits(max_connections=READERS, max_keepalive_connections=READERS)
        async with httpx.AsyncClient(base_url=server, limits=limits, timeout=120) as client:
            tasks = [
                asyncio.create_task(reader(client, PAGES[n % len(PAGES)], stop, answers, n, failed))
                for n in range(READERS)
            ]
            await eventually("every reader to be answered", lambda: min(answers) >= 1, 120 * SECOND)
            start = len(watcher.stamps[CLOCK[0]])
            answered = list(answers)
            for _ in range(3):  # a new episode: a new scene to describe
                answer = await watcher.call("/lab/reset")
                assert answer["values"]["success"], answer
                await watcher.hears(RESET_TICKS, CLOCK[0])
            await eventually(  # and every reader answered again, resets and all
                "every reader to be answered during the resets",
                lambda: all(a > b for a, b in zip(answers, answered, strict=True)),
                120 * SECOND,
            )
            stop.set()
            await asyncio.gather(*tasks)
        clock = watcher.stamps[CLOCK[0]]
        return {
            "clock_during": len(clock) - start,
            "clock_back": sum(b < a for a, b in itertools.pairwise(clock)),
            "clock_in_order": all(b > a or b == 0 for a, b in itertools.pairwise(clock)),
            "answers": sorted(answers)[:: READERS // 10],
            "failed": failed[:5],
        }
    finally:
        await watcher.close()


async def reader(
    client: httpx.AsyncClient,
    path: str,
    stop: asyncio.Event,
    answers: list[int],
    n: int,
    failed: list[str],
) -> None:
    """Read ``path`` again and again until ``stop``; count reader ``n``'s answers, and
    note what failed (a status other than 200, a connection dropped)."""
    while not stop.is_set():
        try:
            answer = await client.get(path)
        except httpx.TransportError as err:
            failed.append(f"{path}: {err!r}")
            continue
        if answer.status_code != 200:
            failed.append(f"{path}: {answer.status_code} {answer.text[:200]}")
        answers[n] += 1


# -- 4. exports -------------------------------------------------------------------------------


BUILT = re.compile(r" INFO labd\.api\.builds: built export (\S+) in ")  # one per build


@pytest.mark.timeout(300 * SECOND)
def test_an_export_is_built_once(served, tmp_path: Path):
    """The same export asked for again is served without being built again, and four
    clients asking at once for a new one share one build, all getting the same bytes:
    three exports asked for eight times, three builds in the lab's log."""
    data = tmp_path / "data"
    lab = served("--no-robots", "--workers", "0", "--log-level", "INFO", data=data)
    filed = lab.labd("demonstrate", "--data", str(data), "--count", "2", "--json")
    assert filed.returncode == 0, filed.stderr
    lab.start()
    ids = [t["id"] for t in lab.get("/api/trials?kind=demonstration")["trials"]]
    assert len(ids) == 2, ids
    figures = asyncio.run(export_requests(lab.server, ids))
    assert lab.process.poll() is None, lab.log[-4000:]
    lab.stop()  # its log read to the end
    built = BUILT.findall(lab.log)
    print("exports:", {k: v for k, v in figures.items() if k != "digests"}, "built:", built)
    assert len(built) == len(set(built)) == 3, built  # the parquet, each trial's lerobot
    assert len(set(figures["digests"])) == 2, figures  # one dataset each, the same every time


async def export_requests(server: str, ids: list[int]) -> dict[str, Any]:
    async with httpx.AsyncClient(base_url=server, timeout=240 * SECOND) as client:

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
        single_first, _ = await get(f"/api/trials/{ids[1]}/export/lerobot")  # its own build
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
PACE = 32  # blocks: between two runs of 32 MiB, the robot must have published


def upload_blocks(between: Callable[[int], None] = lambda n: None) -> Iterator[bytes]:
    """The upload's blocks; ``between(n)`` is called before block ``n`` of every run of
    ``PACE`` blocks."""
    block = hashlib.sha256(b"labd").digest() * (BLOCK // 32)
    for n in range(UPLOAD // BLOCK):
        if n % PACE == 0:
            between(n)
        yield n.to_bytes(8, "big") + block[8:]


@pytest.mark.timeout(300 * SECOND)
def test_a_large_upload_does_not_stall_the_robot(served):
    """A worker uploads a 1 GiB blob: while the lab holds it half-received, a live
    robot's camera and clock go on (each publishes between every two runs of 32 MiB of
    the upload, which waits for them), and the blob is stored."""
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
    assert figures["paced"] == UPLOAD // BLOCK // PACE, figures  # the robot went on each time
    assert lab.process.poll() is None, lab.log[-4000:]
    lab.stop()
    for blob in lab.data.rglob(digest.removeprefix("sha256:") + "*"):
        blob.unlink()  # 1 GiB: a run's folders stay small on a small disk


async def upload(lab: Any, digest: str) -> dict[str, Any]:
    watcher = await Watcher.open(lab.bridge + "/robots/icreate-1", CLOCK, CAMERA)
    paced: list[int] = []

    def robot_went_on(n: int) -> None:
        """On the upload's thread: wait until the robot's clock and camera have each
        published since the last run of blocks (the test's loop notes their messages)."""
        marks = {topic: len(watcher.arrivals[topic]) for topic, _ in (CLOCK, CAMERA)}
        deadline = time.monotonic() + 60 * SECOND
        while any(len(watcher.arrivals[topic]) == mark for topic, mark in marks.items()):
            if time.monotonic() > deadline:
                raise AssertionError(f"the robot stalled with {n} MiB of the upload sent")
            time.sleep(0.005)  # a poll of the test loop's count, not a wait for time
        paced.append(n)

    try:
        await watcher.hears(1, CLOCK[0], CAMERA[0])  # the camera renders for its watcher
        headers = {"Authorization": f"Bearer {lab.token}", PROTOCOL_HEADER: str(PROTOCOL)}
        # on a thread: this loop only reads the robot's messages, and notes them on time
        answer = await asyncio.to_thread(
            httpx.put,
            f"{lab.server}/api/blobs/{digest}",
            content=upload_blocks(robot_went_on),
            headers=headers,
            timeout=240 * SECOND,
        )
        return {"status": answer.status_code, "paced": len(paced)}
    finally:
        await watcher.close()
