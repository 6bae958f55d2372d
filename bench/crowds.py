"""A live lab under crowds and attacks: how fast it stays for everyone else, in one run.

The fault tests (``tests/faults/``) hold what the lab does under each attack: nobody is
starved or locked out, every message arrives in order. How fast it does it depends on
the machine, so it is measured here, each figure against the same figure on the same
lab moments before without the attack (the baseline), and printed as their ratio:

- ``stalled``: 100 clients reading a live maze robot's camera and odometry, alone and
  beside 100 clients subscribed to the camera that never read (``test_crowd.py``);
  messages a second, target: at least 85 % of alone;
- ``readers``: a PR2's ``/clock`` as a WebSocket client sees it, alone and beside 100
  anonymous readers of the pages and the 3D scene while the robot is reset three times
  (``test_dos.py``); ticks a second (target 85 %), the longest gap, the readers' p50/p99;
- ``flood``: a client's odometry and its service calls' round trips, alone and beside a
  client publishing ``/cmd_vel`` as fast as its socket allows (``test_abuse.py``);
  target: 85 % of the rate, a median call under 100 ms and none over 1 s;
- ``slowloris``: another address's home page and bridge connection, alone and during
  1,100 slow connections (``test_dos.py``); seconds, target: a median under 2 s;
- ``upload``: the longest gap in a maze robot's clock and camera over a window alone and
  during a worker's 1 GiB upload (``test_dos.py``); target: under 1.5 s;
- ``auth``: 200 ``/api/auth`` requests at once and 200 bridge clients presenting a key
  at once, alone and while 40 submissions hold every thread of the submissions' pool
  (``test_account_attacks.py``); p99 seconds, target: under 2 s;
- ``exports``: an export asked for again against its first build, four clients asking
  at once for a new one against one build alone; target: under 0.25 and under 2.

    .venv/bin/python bench/crowds.py [--scenarios stalled,readers,...] [--seconds 4]
                                     [--json]

Each scenario starts its own ``labd serve`` (as the fault tests do); progress goes to
stderr, the table (or ``--json``, one object) to stdout.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import hashlib
import itertools
import json
import statistics
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import httpx
import orjson
from websockets.asyncio.client import connect

sys.path[:0] = [str(Path(__file__).resolve().parents[1])]
from labd.service import ServiceConfig  # noqa: E402
from scheduler.remote import PROTOCOL, PROTOCOL_HEADER  # noqa: E402
from tests.faults import test_abuse, test_account_attacks, test_crowd, test_dos  # noqa: E402
from tests.faults.conftest import Served  # noqa: E402

KEPT = 0.85  # share of its rate alone a client keeps under attack (targets of the issues)


def log(*words: object) -> None:
    print(*words, file=sys.stderr, flush=True)


@contextlib.contextmanager
def lab(*args: str, data: Path | None = None) -> Iterator[Served]:
    """A `labd serve` with ``args`` on loopback and free ports, stopped at the end."""
    with tempfile.TemporaryDirectory(prefix="labd-bench-crowds-") as folder:
        served = Served(data or Path(folder) / "data", Path(folder) / "cache", *args)
        try:
            yield served
        finally:
            served.stop()


def row(
    figure: str, alone: float | None, attacked: float, target: str, unit: str = ""
) -> dict[str, Any]:
    """One figure, alone (None: no baseline) and under attack, and their ratio."""
    return {
        "figure": figure,
        "alone": None if alone is None else float(f"{alone:.4g}"),
        "attacked": float(f"{attacked:.4g}"),
        "ratio": round(attacked / alone, 3) if alone else None,
        "unit": unit,
        "target": target,
    }


def gap(times: list[float], start: float, end: float) -> float:
    """The longest time from ``start`` to ``end`` with no arrival in ``times``."""
    inside = [start, *(t for t in times if start <= t < end), end]
    return max(b - a for a, b in itertools.pairwise(inside))


def rate(times: list[float], start: float, end: float) -> float:
    return sum(start <= t < end for t in times) / (end - start)


async def window(seconds: float) -> tuple[float, float]:
    start = time.monotonic()
    await asyncio.sleep(seconds)  # a measurement window
    return start, time.monotonic()


class Arrivals(test_crowd.Healthy):
    """A healthy client of ``test_crowd`` that also notes when each message came."""

    def __init__(self, ws: Any) -> None:
        self.times: dict[str, list[float]] = {topic: [] for topic in test_crowd.TOPICS}
        super().__init__(ws)

    async def _read(self) -> None:
        async for frame in self.ws:
            message = orjson.loads(frame)
            if message["op"] == "publish":
                self.times[message["topic"]].append(time.monotonic())
                self.counts[message["topic"]] += 1
            else:
                await self.replies.put(message)


# -- stalled readers ---------------------------------------------------------------------


def stalled(seconds: float) -> list[dict[str, Any]]:
    with lab(
        "--robot", "icreate-1=icreate-maze", "--no-playground", "--workers", "0",
        "--max-connections-per-address", "0",
    ) as served:  # fmt: skip
        served.start()
        path = "/robots/icreate-1"
        port = int(served.bridge.rsplit(":", 1)[1])
        return asyncio.run(_stalled(served.bridge + path, port, path, seconds))


async def _stalled(url: str, port: int, path: str, seconds: float) -> list[dict[str, Any]]:
    clients = [
        Arrivals(await connect(url, max_size=None, compression=None))
        for _ in range(test_crowd.HEALTHY)
    ]
    socks = []
    try:
        for client in clients:
            await client.subscribe()
        await asyncio.sleep(1.0)  # the camera starts rendering for its watchers
        alone = await window(seconds)
        socks = await asyncio.gather(
            *(
                asyncio.to_thread(test_crowd.stalled_client, port, path)
                for _ in range(test_crowd.STALLED)
            )
        )
        await asyncio.sleep(1.0)  # every stalled subscription in
        beside = await window(seconds)
    finally:
        for sock in socks:
            sock.close()
        for client in clients:
            await client.ws.close()
            client.reader.cancel()
    rows = []
    for topic in test_crowd.TOPICS:
        before = statistics.mean(rate(c.times[topic], *alone) for c in clients)
        after = [rate(c.times[topic], *beside) for c in clients]
        rows.append(row(f"{topic}, mean of 100 readers", before, statistics.mean(after),
                        f">= {KEPT:.0%} of alone", "Hz"))  # fmt: skip
        rows.append(row(f"{topic}, slowest reader", before, min(after), "", "Hz"))
    return rows


# -- readers of pages and the scene --------------------------------------------------------


def readers(seconds: float) -> list[dict[str, Any]]:
    with lab("--robot", "pr2-1=pr2-table", "--no-playground", "--workers", "0") as served:
        served.start()
        return asyncio.run(_readers(served.server, served.bridge + "/robots/pr2-1", seconds))


async def _readers(server: str, bridge: str, seconds: float) -> list[dict[str, Any]]:
    watcher = await test_dos.Watcher.open(bridge, test_dos.CLOCK)
    clock = watcher.arrivals["/clock"]
    try:
        await asyncio.sleep(2.0)  # the robot steps once someone listens
        alone = await window(seconds)
        stop = asyncio.Event()
        latencies: list[float] = []
        limits = httpx.Limits(max_connections=test_dos.READERS)
        async with httpx.AsyncClient(base_url=server, limits=limits, timeout=120) as client:

            async def read(path: str) -> None:
                while not stop.is_set():
                    began = time.monotonic()
                    (await client.get(path)).raise_for_status()
                    latencies.append(time.monotonic() - began)

            tasks = [
                asyncio.create_task(read(test_dos.PAGES[n % len(test_dos.PAGES)]))
                for n in range(test_dos.READERS)
            ]
            await asyncio.sleep(2.0)  # every reader at it
            latencies.clear()
            start = time.monotonic()
            for _ in range(3):  # a new episode: a new scene to describe
                await watcher.call("/lab/reset")
                await asyncio.sleep(seconds / 2)  # a measurement window
            end = time.monotonic()
            stop.set()
            await asyncio.gather(*tasks)
    finally:
        await watcher.close()
    timed = sorted(latencies)
    return [
        row("/clock, ticks a second", rate(clock, *alone), rate(clock, start, end),
            f">= {KEPT:.0%} of alone", "Hz"),
        row("/clock, longest gap (resets included)", gap(clock, *alone), gap(clock, start, end),
            "", "s"),
        row("a reader's request, p50", None, timed[len(timed) // 2], "", "s"),
        row("a reader's request, p99", None, timed[int(len(timed) * 0.99)], "", "s"),
    ]  # fmt: skip


# -- a flooding client ---------------------------------------------------------------------


def flood(seconds: float) -> list[dict[str, Any]]:
    with lab("--robot", "icreate-1=icreate-maze", "--no-playground", "--workers", "0") as served:
        served.start()
        port = int(served.bridge.rsplit(":", 1)[1])
        return asyncio.run(_flood(served.bridge + "/robots/icreate-1", port, seconds))


async def _calls(client: Arrivals, seconds: float) -> tuple[list[float], tuple[float, float]]:
    """Service calls back to back for ``seconds``: each round trip, and the window."""
    calls = []
    start = time.monotonic()
    while time.monotonic() - start < seconds:
        began = time.monotonic()
        await client.call("/rosapi/get_time")
        calls.append(time.monotonic() - began)
    return sorted(calls), (start, time.monotonic())


async def _flood(url: str, port: int, seconds: float) -> list[dict[str, Any]]:
    async with connect(url, max_size=None) as ws:
        client = Arrivals(ws)
        frame = {"op": "subscribe", "topic": "/odom", "type": "nav_msgs/msg/Odometry"}
        await ws.send(orjson.dumps(frame).decode())
        await asyncio.sleep(1.0)  # the robot steps once someone listens
        calm, alone = await _calls(client, seconds)
        stop, sent = threading.Event(), [0]
        flooder = threading.Thread(target=test_abuse.flood, args=(port, stop, sent), daemon=True)
        flooder.start()
        await asyncio.sleep(0.5)  # the flood under way
        flooded, during = await _calls(client, seconds)
        stop.set()
        flooder.join(10)
        client.reader.cancel()
    odom = client.times["/odom"]
    return [
        row("/odom", rate(odom, *alone), rate(odom, *during), f">= {KEPT:.0%} of alone", "Hz"),
        row("a service call, median", statistics.median(calm), statistics.median(flooded),
            "< 0.1 s", "s"),
        row("a service call, slowest", calm[-1], flooded[-1], "< 1 s", "s"),
        row("flood frames sent a second", None, sent[0] / (during[1] - during[0]), "", "/s"),
    ]  # fmt: skip


# -- slowloris -----------------------------------------------------------------------------


def slowloris(seconds: float) -> list[dict[str, Any]]:
    with lab(
        "--robot", "icreate-1=icreate-maze", "--no-playground", "--workers", "0",
        "--header-timeout", str(test_dos.HEADER_TIMEOUT),
    ) as served:  # fmt: skip
        with test_dos.open_files_limit(1024):
            served.start()
        return asyncio.run(_slowloris(served.server, served.bridge + "/robots/icreate-1", seconds))


async def _bystander(server: str, bridge: str, tries: int, pause: float) -> dict[str, list[float]]:
    transport = httpx.AsyncHTTPTransport(local_address=test_dos.BYSTANDER)
    found: dict[str, list[float]] = {"page": [], "bridge": []}
    async with httpx.AsyncClient(transport=transport, timeout=60) as client:
        for _ in range(tries):
            began = time.monotonic()
            (await client.get(server + "/", headers={"Connection": "close"})).raise_for_status()
            found["page"].append(time.monotonic() - began)
            began = time.monotonic()
            async with await test_dos.bridge_client(bridge, test_dos.BYSTANDER, open_timeout=60):
                found["bridge"].append(time.monotonic() - began)
            await asyncio.sleep(pause)  # the bystander's pace
    return found


async def _slowloris(server: str, bridge: str, seconds: float) -> list[dict[str, Any]]:
    alone = await _bystander(server, bridge, 3, 0.5)
    attack = test_dos.Attack()
    ports = (test_dos.port_of(server), test_dos.port_of(bridge))
    slow = [
        asyncio.create_task(test_dos.slow_client(ports[i % 2], attack))
        for i in range(test_dos.SLOW)
    ]
    try:
        await asyncio.sleep(seconds)  # the attack in full swing
        attacked = await _bystander(server, bridge, 3, seconds)
    finally:
        attack.end()
        attack.let_go = time.monotonic()  # the bench does not wait for the lab's cuts
        await asyncio.gather(*slow)
    held = sorted(e.seconds for e in attack.ended if e.by_lab)
    return [
        row("another address's /, median of 3", statistics.median(alone["page"]),
            statistics.median(attacked["page"]), "< 2 s", "s"),
        row("its bridge connection, median of 3", statistics.median(alone["bridge"]),
            statistics.median(attacked["bridge"]), "< 2 s", "s"),
        row("longest a slow connection was kept (cut by the lab)", test_dos.HEADER_TIMEOUT,
            held[-1], "< header timeout + 2 s", "s"),
    ]  # fmt: skip


# -- a large upload ------------------------------------------------------------------------


def upload(seconds: float) -> list[dict[str, Any]]:
    with lab("--robot", "icreate-1=icreate-maze", "--no-playground", "--workers", "0") as served:
        served.token = served.add_user("worker", "--worker")
        served.start()
        sha = hashlib.sha256()
        for block in test_dos.upload_blocks():
            sha.update(block)
        return asyncio.run(_upload(served, f"sha256:{sha.hexdigest()}", seconds))


async def _upload(served: Served, digest: str, seconds: float) -> list[dict[str, Any]]:
    watcher = await test_dos.Watcher.open(
        served.bridge + "/robots/icreate-1", test_dos.CLOCK, test_dos.CAMERA
    )
    try:
        await asyncio.sleep(2.0)  # the camera renders for its watcher
        alone = await window(seconds)
        headers = {"Authorization": f"Bearer {served.token}", PROTOCOL_HEADER: str(PROTOCOL)}
        start = time.monotonic()
        answer = await asyncio.to_thread(  # on a thread: this loop notes messages on time
            httpx.put,
            f"{served.server}/api/blobs/{digest}",
            content=test_dos.upload_blocks(),
            headers=headers,
            timeout=600,
        )
        end = time.monotonic()
        answer.raise_for_status()
        await asyncio.sleep(1.0)  # the messages of the last moment arrive
    finally:
        await watcher.close()
    rows = []
    for topic, _ in (test_dos.CLOCK, test_dos.CAMERA):
        times = watcher.arrivals[topic]
        rows.append(row(f"{topic}, longest gap", gap(times, *alone), gap(times, start, end),
                        "< 1.5 s", "s"))  # fmt: skip
    rows.append(row("the upload, MiB a second", None, 1024 / (end - start), "", "MiB/s"))
    return rows


# -- the authorizer ------------------------------------------------------------------------


def auth(seconds: float) -> list[dict[str, Any]]:
    del seconds  # 200 requests at once, twice: no window
    args = (*test_account_attacks.ARGS, "--fetch-timeout", "3600", "--resolve-timeout", "3600",
            "--allow-private-hosts")  # fmt: skip
    with lab(*args) as served:
        served.start()
        served.token = test_account_attacks.add_user(served, "alice", "correct horse battery")
        made = test_account_attacks.book(served, served.token, minutes=30)
        made.raise_for_status()
        key = made.json()["key"]["key"]
        alone = asyncio.run(test_account_attacks.authorize_200(served, key))
        silent = test_account_attacks.Silent()
        pool = ThreadPoolExecutor(40)
        try:
            for n in range(40):
                pool.submit(
                    httpx.post,
                    f"{served.server}/api/trials",
                    json={"repository": f"git://127.0.0.1:{silent.port}/r{n}.git"},
                    headers={"Authorization": f"Bearer {served.token}"},
                    timeout=None,
                )
            threads = ServiceConfig().submit_threads
            while silent.accepted < threads:  # every thread of the pool held
                time.sleep(0.05)
            held = asyncio.run(test_account_attacks.authorize_200(served, key))
        finally:
            silent.close()
            pool.shutdown(wait=True)
    p99 = test_account_attacks.p99
    return [
        row("/api/auth, 200 at once, p99", p99(alone[0]), p99(held[0]), "< 2 s", "s"),
        row("a key on the bridge, 200 at once, p99", p99(alone[1]), p99(held[1]), "< 2 s", "s"),
    ]


# -- exports -------------------------------------------------------------------------------


def exports(seconds: float) -> list[dict[str, Any]]:
    del seconds
    with tempfile.TemporaryDirectory(prefix="labd-bench-exports-") as folder:
        data = Path(folder) / "data"
        with lab("--no-robots", "--workers", "0", data=data) as served:
            served.labd("demonstrate", "--data", str(data), "--count", "2", "--json")
            served.start()
            ids = [t["id"] for t in served.get("/api/trials?kind=demonstration")["trials"]]
            figures = asyncio.run(test_dos.export_requests(served.server, ids))
    return [
        row("a many-trial export: again / first", figures["first"], figures["again"],
            "< 0.25", "s"),
        row("a new export asked by four at once / one build", figures["single_first"],
            figures["four_at_once"], "< 2", "s"),
        row("a single-trial export: again / first", figures["single_first"],
            figures["single_again"], "< 0.25", "s"),
    ]  # fmt: skip


SCENARIOS: dict[str, Callable[[float], list[dict[str, Any]]]] = {
    "stalled": stalled,
    "readers": readers,
    "flood": flood,
    "slowloris": slowloris,
    "upload": upload,
    "auth": auth,
    "exports": exports,
}


def table(results: dict[str, list[dict[str, Any]]]) -> str:
    lines = [
        f"{'scenario':10} {'figure':52} {'alone':>9} {'attacked':>9} {'ratio':>7}  target",
    ]
    for name, rows in results.items():
        for r in rows:
            ratio = "" if r["ratio"] is None else f"{r['ratio']:.2f}"
            alone = "" if r["alone"] is None else f"{r['alone']:.3g}"
            figure = f"{r['figure']} ({r['unit']})" if r["unit"] else r["figure"]
            lines.append(
                f"{name:10} {figure:52} {alone:>9} {r['attacked']:>9.3g} {ratio:>7}  {r['target']}"
            )
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenarios", default=",".join(SCENARIOS), help="comma-separated")
    parser.add_argument("--seconds", type=float, default=4.0, help="each measurement window")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    results = {}
    for name in args.scenarios.split(","):
        log(f"{name} ...")
        began = time.monotonic()
        results[name] = SCENARIOS[name](args.seconds)
        log(f"{name}: {time.monotonic() - began:.0f} s")
    print(json.dumps(results, indent=2) if args.json else table(results))


if __name__ == "__main__":
    main()
