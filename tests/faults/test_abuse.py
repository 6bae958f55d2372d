"""Controllers and clients that abuse the bridge.

In a real sandboxed trial, a controller (``abuser/``) floods the bridge with
publishes while a second connection of its own times round trips, subscribes to more
topics than a client may, and tries to provide every service name of the lab, as a
service and as an action; then it steps three times as an honest one does. Each abuse
is refused or absorbed, the trial ends as it would have, and its data digest is the
honest run's. On a live robot of `labd serve`, a client that publishes as fast as its
socket allows does not slow another client's odometry or service calls.
"""

from __future__ import annotations

import asyncio
import itertools
import json
import shutil
import socket
import threading
import time
from pathlib import Path
from typing import Any

import orjson
import pytest
from websockets.asyncio.client import connect

from labd.graph.graph import Side
from labd.recorder import read_channels
from repository.trial import Order, Outcome
from scheduler.runner import run_trial
from tests.faults.test_crowd import Healthy
from tests.helpers.sandboxes import make_backend
from tests.helpers.timing import SECOND, eventually

pytestmark = [pytest.mark.integration, pytest.mark.rates]
ABUSER = Path(__file__).resolve().parent / "abuser"
FLOOD, SUBSCRIPTIONS, MAX_SUBSCRIPTIONS = 20_000, 1_500, 1_000


def run(cache, host, tmp_path: Path, mode: str):
    folder = tmp_path / mode
    shutil.copytree(ABUSER, folder)
    toml = folder / "lab.toml"
    toml.write_text(toml.read_text().replace('"abuse"', f'"{mode}"'))
    folder.chmod(0o755)
    backend = make_backend("bwrap", cache)
    order = Order(repository=str(folder), seed=2)
    return asyncio.run(
        run_trial(order, backend=backend, host=host, out=tmp_path / f"{mode}-run", cache=cache)
    )


@pytest.mark.timeout(180)
def test_an_abusive_controller_changes_nothing_but_its_own_topic(cache, host, tmp_path: Path):
    """Flooding, 1,500 subscriptions and every lab name to provide: the bridge answers the
    controller's other connection again and again during the flood, 500 subscriptions and
    every name are refused with a status, /lab/step stays the lab's, and the record's data
    equals an honest run's."""
    abusive = run(cache, host, tmp_path, "abuse")
    honest = run(cache, host, tmp_path, "honest")
    for result in (abusive, honest):
        assert result.outcome is Outcome.FAIL, result.reason
        assert result.reason.startswith("the controller exited with 0 at tick 3"), result.reason
    assert abusive.data_digest == honest.data_digest
    report = json.loads((abusive.folder / "controller.stdout.log").read_text())
    probe = report["probe"]
    print(
        f"flood of {FLOOD} publishes: {report['flood_seconds']:.2f} s "
        f"({FLOOD / report['flood_seconds']:,.0f}/s); the other connection's round trips "
        f"meanwhile: {probe['round_trips']}, median {probe['median'] * 1e3:.1f} ms, "
        f"max {probe['max'] * 1e3:.1f} ms; {len(report['names'])} lab names tried as services"
        " and as actions"
    )
    assert probe["round_trips"] >= 5, probe  # answered during the flood (how fast: bench/)
    flooded = {c.topic: c for c in read_channels(abusive.folder)}["/flood"]
    assert (flooded.side, flooded.message_count) == (Side.CLIENT, FLOOD)  # all recorded

    refused = report["subscriptions_refused"]
    assert sorted(refused) == sorted(f"sub-{i}" for i in range(MAX_SUBSCRIPTIONS, SUBSCRIPTIONS))
    assert set(refused.values()) == {
        f"subscribe: too many subscriptions (the limit is {MAX_SUBSCRIPTIONS})"
    }

    names = report["names"]
    assert {"/lab/step", "/rosapi/topics", "/rosapi/get_param", "lab/step"} <= set(names)
    assert sorted(report["names_refused"]) == sorted(
        f"{kind} {name}" for name in names for kind in ("service", "action")
    )
    for attempt, message in report["names_refused"].items():
        kind, name = attempt.split(" ", 1)
        absolute = name if name.startswith("/") else f"/{name}"
        assert message.startswith(f"advertise_{kind}: "), message
        assert f"{absolute} belongs to the lab" in message, message
    assert report["step_providers"] == ["/robot"]
    assert report["other_statuses"] == []


@pytest.mark.timeout(120)
def test_a_flooding_client_does_not_slow_a_live_robots_other_clients(served):
    """A client publishing /cmd_vel as fast as its socket allows, never reading: while it
    floods, another client hears 40 odometry messages, in order, and has 20 service calls
    answered back to back, and the flood goes on meanwhile (the lab reads it)."""
    lab = served("--robot", "icreate-1=icreate-maze", "--no-playground", "--workers", "0").start()
    port = int(lab.bridge.rsplit(":", 1)[1])
    figures = asyncio.run(flooded(lab.bridge + "/robots/icreate-1", port))
    print("flooding client:", figures)
    assert figures["published_before"] >= FLOODED, figures
    assert figures["published_during"] > 0, figures  # the lab read the flood meanwhile
    assert figures["odom_flooded"] >= ODOM and figures["odom_in_order"], figures
    assert figures["calls"] >= CALLS, figures
    assert lab.process.poll() is None, lab.log


FLOODED = 10_000  # /cmd_vel frames the flooding client has sent before the other one is heard
ODOM, CALLS = 40, 20  # what the other client must get while the flood goes on


async def flooded(url: str, port: int) -> dict[str, Any]:
    async with connect(url, max_size=None) as ws:
        healthy = Healthy(ws)
        frame = {"op": "subscribe", "topic": "/odom", "type": "nav_msgs/msg/Odometry"}
        await ws.send(orjson.dumps(frame).decode())
        await eventually("the robot's odometry", lambda: healthy.counts["/odom"] >= ODOM)
        stop = threading.Event()
        sent = [0]
        flooder = threading.Thread(target=flood, args=(port, stop, sent), daemon=True)
        flooder.start()
        try:
            await eventually(f"{FLOODED} frames of the flood", lambda: sent[0] >= FLOODED)
            before, published, calls = healthy.counts["/odom"], sent[0], []
            deadline = time.monotonic() + 60 * SECOND
            while len(calls) < CALLS or healthy.counts["/odom"] - before < ODOM:
                start = time.monotonic()  # calls back to back while the flood goes on
                answer = await healthy.call("/rosapi/get_time")
                assert answer["result"] is True, answer
                calls.append(time.monotonic() - start)
                assert time.monotonic() < deadline, (len(calls), healthy.counts)
            odom = healthy.counts["/odom"] - before
            during = sent[0] - published
        finally:
            stop.set()
            flooder.join(10)
            healthy.reader.cancel()
    calls.sort()
    stamps = healthy.stamps["/odom"]
    return {
        "odom_flooded": odom,
        # rising, or back to 0 once: the flooder's commands take the robot (a new episode)
        "odom_in_order": all(a < b or b == 0 for a, b in itertools.pairwise(stamps))
        and sum(b < a for a, b in itertools.pairwise(stamps)) <= 1,
        "calls": len(calls),
        "call_median": round(calls[len(calls) // 2], 4),
        "call_max": round(calls[-1], 4),
        "published_before": published,
        "published_during": during,
    }


def flood(port: int, stop: threading.Event, sent: list[int]) -> None:
    """Publish /cmd_vel frames back to back on a raw socket that never reads; ``sent[0]``
    counts them."""
    sock = socket.create_connection(("127.0.0.1", port))
    sock.sendall(
        b"GET /robots/icreate-1 HTTP/1.1\r\nHost: x\r\nUpgrade: websocket\r\n"
        b"Connection: Upgrade\r\nSec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\n"
        b"Sec-WebSocket-Version: 13\r\n\r\n"
    )
    answer = b""
    while b"\r\n\r\n" not in answer:
        answer += sock.recv(1)
    assert b" 101 " in answer
    payload = orjson.dumps(
        {"op": "publish", "topic": "/cmd_vel", "msg": {"linear": {"x": 0.1}, "angular": {"z": 0.2}}}
    )
    frame = bytes([0x81, 0x80 | len(payload)]) + b"\x00\x00\x00\x00" + payload
    batch = frame * 500
    try:
        while not stop.is_set():
            sock.sendall(batch)
            sent[0] += 500
    finally:
        sock.close()
