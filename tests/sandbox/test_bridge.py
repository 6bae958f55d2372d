"""The one way out: ws://127.0.0.1:9090 inside, relayed by the launcher to the host's socket."""

from __future__ import annotations

import asyncio
import json
import statistics
import time
import uuid
from pathlib import Path

import pytest
from websockets.sync.client import unix_connect

from sandbox.api import Limits
from tests.sandbox.conftest import Bridge, Controllers

pytestmark = [pytest.mark.integration, pytest.mark.timeout(300)]

ROUND_TRIPS = 300


async def test_the_bridge_is_reached(controllers: Controllers, bridge: Bridge) -> None:
    """A controller reaches the host's bridge socket at LAB_BRIDGE_URL, both ways, and at
    LAB_BRIDGE_HOST and LAB_BRIDGE_PORT, the same in two parts."""
    ended = await controllers.run(
        """
        import os
        from websockets.sync.client import connect
        print(os.environ["LAB_BRIDGE_URL"])
        with connect(os.environ["LAB_BRIDGE_URL"]) as ws:
            ws.send("ping")
            print(ws.recv())
        host, port = os.environ["LAB_BRIDGE_HOST"], os.environ["LAB_BRIDGE_PORT"]
        with connect(f"ws://{host}:{port}") as ws:
            ws.send("pong")
            print(ws.recv())
        """,
        bridge=bridge,
    )
    assert ended.code == 0, ended.stderr
    assert ended.stdout == b"ws://127.0.0.1:9090\necho:ping\necho:pong\n"
    assert bridge.received.get_nowait() == "ping"


async def test_many_connections_and_large_messages(
    controllers: Controllers, bridge: Bridge
) -> None:
    """Eight connections at once each carry a 4 MiB message there and back intact."""
    ended = await controllers.run(
        """
        import hashlib, os
        from concurrent.futures import ThreadPoolExecutor
        from websockets.sync.client import connect

        def round_trip(i):
            message = (str(i) * 4 * 1024 * 1024)[: 4 * 1024 * 1024]
            with connect(os.environ["LAB_BRIDGE_URL"], max_size=None) as ws:
                ws.send(message)
                return ws.recv() == "echo:" + message

        with ThreadPoolExecutor(8) as pool:
            print(list(pool.map(round_trip, range(8))))
        """,
        bridge=bridge,
        limits=Limits(wall=120),
    )
    assert ended.code == 0, ended.stderr
    assert ended.stdout == b"[True, True, True, True, True, True, True, True]\n"


async def test_what_a_controller_sends_as_it_exits_arrives(
    controllers: Controllers, workdir: Path
) -> None:
    """8 MiB sent right before the controller exits reach a bridge slower than it, whole."""
    path = workdir / f"slow-{uuid.uuid4().hex[:8]}.sock"
    received = 0
    ended_connection = asyncio.Event()

    async def slow_bridge(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        nonlocal received
        while data := await reader.read(64 * 1024):
            received += len(data)
            await asyncio.sleep(0.001)  # a throttle, so the relay holds data when the job ends
        ended_connection.set()
        writer.close()

    async with await asyncio.start_unix_server(slow_bridge, str(path)):
        ended = await controllers.run(
            """
            import os, socket
            connection = socket.create_connection(("127.0.0.1", 9090))
            connection.sendall(b"x" * 8 * 1024 * 1024)
            os._exit(0)
            """,
            bridge=Bridge(path),
        )
        await asyncio.wait_for(ended_connection.wait(), 30)
    assert ended.code == 0, ended.stderr
    assert received == 8 * 1024 * 1024


async def test_the_relay_adds_little_latency(controllers: Controllers, bridge: Bridge) -> None:
    """A request and its reply through the launcher take under 1 ms more than on the host."""
    ended = await controllers.run(
        f"""
        import json, os, time
        from websockets.sync.client import connect
        with connect(os.environ["LAB_BRIDGE_URL"]) as ws:
            times = []
            for i in range({ROUND_TRIPS}):
                started = time.perf_counter()
                ws.send("step")
                ws.recv()
                times.append(time.perf_counter() - started)
        print(json.dumps(times))
        """,
        bridge=bridge,
    )
    assert ended.code == 0, ended.stderr
    inside = statistics.median(json.loads(ended.stdout)[20:])

    def on_the_host() -> list[float]:
        with unix_connect(str(bridge.socket)) as ws:
            times = []
            for _ in range(ROUND_TRIPS):
                started = time.perf_counter()
                ws.send("step")
                ws.recv()
                times.append(time.perf_counter() - started)
        return times

    direct = statistics.median((await asyncio.to_thread(on_the_host))[20:])
    assert inside - direct < 0.001, (inside, direct)


async def test_without_a_bridge_nothing_listens(controllers: Controllers) -> None:
    """A job without a bridge socket has no LAB_BRIDGE_URL and nothing on port 9090."""
    ended = await controllers.run(
        """
        import os, socket
        print(os.environ.get("LAB_BRIDGE_URL"))
        try:
            socket.create_connection(("127.0.0.1", 9090), timeout=2).close()
            print("connected")
        except OSError as err:
            print(type(err).__name__)
        """
    )
    assert ended.code == 0, ended.stderr
    assert ended.stdout == b"None\nConnectionRefusedError\n"
