"""A live robot's camera to many viewers, and command-to-pixel latency, over rosbridge
and over Foxglove's WebSocket protocol.

``labd serve`` hosts one maze robot (its camera at 640x480) in a child process. Ten
viewers, roslibjs clients in one Node process (``bench/live_viewers.mjs``, npm
``roslib`` 2.x from ``tests/js/node_modules``; ten headless Chromium pages do not fit
on this 2-core machine beside the lab), subscribe to the camera for a while;
meanwhile a driver (a rosbridge client in this process) takes control with
``/lab/drive`` and, again and again, waits until the picture is still, commands a turn
on ``/cmd_vel`` and times the first camera frame whose pixels moved: the
command-to-pixel latency (the same path as a key press in the page, minus the
browser's own key handling and drawing, which the page reports as its "latency" UX
event). Measured: frames per second each viewer received, latency p50/p99, the
server's CPU (share of one core) and peak RSS; the baseline is the same with no
viewer. The maze's control rate sets the camera's: 30 Hz is not one (a tick is a
whole number of 2 ms steps), so ``--rate 25`` (default) or 50.

The same robot is then watched by Foxglove viewers (``bench/live_foxglove_viewers.mjs``:
``@foxglove/ws-protocol``'s client offering ``foxglove.sdk.v1``, decoding one frame in
ten with Foxglove's ROS 2 reader) and driven over Foxglove's protocol (a client in this
process: subscribes the camera's channel, calls ``/lab/drive``, advertises ``/cmd_vel``
in CDR or JSON and publishes the turns on it), with the same criterion of a moved
picture. The phases, each ``--seconds / --rounds`` long, take turns round by round
(the order of the two protocols swapped every round) so that both share the machine's
state: a baseline driven over each protocol, rosbridge viewers with the rosbridge
driver, Foxglove viewers with the Foxglove driver. Each drive starts a new episode, the
next seed: another maze and start, and how far a turn moves the picture in one tick
depends on what the camera sees, so a phase's latencies also depend on its scenes;
many short rounds average them; the latency to the first change of the picture depends
on them less. The frame lag is free of the scene: each camera frame the driver
received, its arrival less its stamp (simulation time, which a live robot keeps to the
wall clock), above the least of its phase: how late frames come. Peak RSS is the
server's over a phase; one process serves every phase, so it only grows from one phase
to the next.

    .venv/bin/python bench/live.py [--viewers 10] [--foxglove-viewers 10] [--seconds 20]
        [--rounds 4] [--rate 25] [--foxglove-encoding cdr] [--seed 0] [--json]
"""

from __future__ import annotations

import argparse
import asyncio
import base64
import io
import json
import os
import random
import re
import socket
import statistics
import subprocess
import sys
import time
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

import numpy as np
import orjson
import psutil
import websockets
from PIL import Image
from rosbags.typesys import Stores, get_typestore
from websockets.typing import Subprotocol

from labd.bridge.foxglove import wire

ROOT = Path(__file__).resolve().parents[1]
MOVED = 3.0  # mean absolute difference (0..255) of a 160x120 grey picture: it moved
CHANGED = 0.5  # ... it changed at all (a still picture's frames differ by less)
CAMERA = "/camera/image/compressed"
WHO = {"session": "bench", "interface": "video", "user": "bench"}
TYPES = get_typestore(Stores.ROS2_JAZZY)
Frames = asyncio.Queue[tuple[float, np.ndarray]]
Command = Callable[[float], Awaitable[None]]
# latencies and to the first change (ms); frames' arrival less their stamps (s)
Driven = tuple[tuple[list[float], list[float]], list[float]]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def start_lab(rate: int, data: Path) -> tuple[subprocess.Popen[bytes], str]:
    port = free_port()
    command = [
        str(ROOT / ".venv" / "bin" / "labd"), "serve", "--no-service", "--no-playground",
        "--robot", "icreate-1=icreate-maze", "--bridge-port", str(port), "--data", str(data),
        "--param", "camera_width=640", "--param", "camera_height=480",
        "--param", f"control_rate={rate}",
    ]  # fmt: skip
    lab = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL)
    assert lab.stdout is not None
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        line = lab.stdout.readline().decode()
        if re.search(r"ws://127\.0\.0\.1:\d+/robots/icreate-1", line):
            return lab, f"ws://127.0.0.1:{port}/robots/icreate-1"
        if not line and lab.poll() is not None:
            break
    lab.kill()
    raise SystemExit("labd serve did not start")


def grey(jpeg: bytes) -> np.ndarray:
    image = Image.open(io.BytesIO(jpeg))
    image.draft("L", (160, 120))
    return np.asarray(image.convert("L").resize((160, 120)), dtype=np.float32)


async def turns(
    frames: Frames, command: Command, seconds: float, period: float, rng: random.Random
) -> tuple[list[float], list[float]]:
    """Command-to-pixel latencies (ms), and to the first change: a turn commanded while
    the picture is still, to the first frame that moved; ``command(z)`` sends a turn at
    ``z`` rad/s, 0 to stop.
    Each turn waits a random part of a frame's ``period`` after a frame, as a key is
    pressed at any moment: sent at once, every command would meet the robot's tick at
    the same phase, and the latencies of a run would sit on one side of a tick or the
    other by chance. How many ticks a turn takes to move the picture by ``MOVED``
    depends on the scene; the first change (``CHANGED``) depends on it less."""
    latencies: list[float] = []
    changes: list[float] = []
    end = time.monotonic() + seconds
    turn = 2.0
    while time.monotonic() < end:
        still = await settle(frames)
        await asyncio.sleep(rng.uniform(0, period))
        turn = -turn
        sent = time.perf_counter()
        await command(turn)
        changed = False
        while True:
            arrived, picture = await asyncio.wait_for(frames.get(), 5)
            difference = float(np.abs(picture - still).mean())
            if difference > CHANGED and not changed and arrived > sent:
                changes.append((arrived - sent) * 1000)
                changed = True
            if difference > MOVED:
                latencies.append((arrived - sent) * 1000)
                break
            if arrived - sent > 0.2:  # keep the turn going, as a held key does
                await command(turn)
        await command(0.0)
    return latencies, changes


async def settle(frames: Frames) -> np.ndarray:
    """The picture once three frames in a row have not moved."""
    last = (await frames.get())[1]
    calm = 0
    while calm < 3:
        picture = (await frames.get())[1]
        calm = calm + 1 if float(np.abs(picture - last).mean()) < 0.5 else 0
        last = picture
    while not frames.empty():  # the newest still frame
        last = frames.get_nowait()[1]
    return last


def seconds_of(stamp: Any) -> float:
    """A ``builtin_interfaces/Time`` (JSON or rosbags) in seconds."""
    if isinstance(stamp, dict):
        return float(stamp["sec"]) + stamp["nanosec"] / 1e9
    return float(stamp.sec) + stamp.nanosec / 1e9


async def drive_rosbridge(url: str, seconds: float, period: float, rng: random.Random) -> Driven:
    """The latencies of a driver that speaks rosbridge (JSON, the JPEG in base64), and
    its camera frames' lags."""
    async with websockets.connect(url, max_size=None) as ws:
        send = lambda m: ws.send(orjson.dumps(m).decode())  # noqa: E731
        await send({"op": "subscribe", "topic": CAMERA, "queue_length": 1})
        await send({"op": "call_service", "service": "/lab/drive", "id": "d", "args": WHO})
        await send({"op": "advertise", "topic": "/cmd_vel", "type": "geometry_msgs/msg/Twist"})
        frames: Frames = asyncio.Queue()
        lags: list[float] = []

        driving = asyncio.Event()

        async def receive() -> None:
            async for text in ws:
                message = orjson.loads(text)
                if message.get("id") == "d" and message.get("op") == "service_response":
                    driving.set()
                elif message.get("topic") == CAMERA:
                    arrived, image = time.perf_counter(), message["msg"]
                    lags.append(arrived - seconds_of(image["header"]["stamp"]))
                    frames.put_nowait((arrived, grey(base64.b64decode(image["data"]))))

        async def command(z: float) -> None:
            msg = {"angular": {"z": z}} if z else {}
            await send({"op": "publish", "topic": "/cmd_vel", "msg": msg})

        reader = asyncio.create_task(receive())
        try:
            await asyncio.wait_for(driving.wait(), 10)
            lags.clear()  # frames of the episode before the drive's
            return await turns(frames, command, seconds, period, rng), lags
        finally:
            reader.cancel()


def twist_cdr(z: float) -> bytes:
    vector = TYPES.types["geometry_msgs/msg/Vector3"]
    twist = TYPES.types["geometry_msgs/msg/Twist"](vector(0.0, 0.0, 0.0), vector(0.0, 0.0, z))
    return bytes(TYPES.serialize_cdr(twist, "geometry_msgs/msg/Twist"))


async def drive_foxglove(
    url: str, seconds: float, period: float, rng: random.Random, encoding: str
) -> Driven:
    """The latencies of a driver that speaks Foxglove's protocol (binary frames, the
    camera in CDR, ``/cmd_vel`` published on a channel of its own in ``encoding``)."""
    offered = [Subprotocol(wire.SDK)]
    async with websockets.connect(url, subprotocols=offered, max_size=None) as ws:
        channels: dict[str, int] = {}
        services: dict[str, int] = {}
        known = asyncio.Event()
        answered: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        frames: Frames = asyncio.Queue()
        lags: list[float] = []
        camera_sub, cmd_vel = 1, 1

        async def receive() -> None:
            async for data in ws:
                if isinstance(data, bytes):
                    if (
                        data[0] == wire.MESSAGE_DATA
                        and int.from_bytes(data[1:5], "little") == camera_sub
                    ):
                        arrived = time.perf_counter()
                        image = TYPES.deserialize_cdr(data[13:], "sensor_msgs/msg/CompressedImage")
                        lags.append(arrived - seconds_of(image.header.stamp))
                        frames.put_nowait((arrived, grey(image.data.tobytes())))
                    elif data[0] == wire.SERVICE_CALL_RESPONSE and not answered.done():
                        answered.set_result(None)
                    continue
                message = orjson.loads(data)
                op = message["op"]
                if op == "advertise":
                    channels.update({c["topic"]: c["id"] for c in message["channels"]})
                elif op == "advertiseServices":
                    services.update({s["name"]: s["id"] for s in message["services"]})
                elif op == "serviceCallFailure" and not answered.done():
                    answered.set_exception(RuntimeError(message["message"]))
                elif op == "status":
                    print(f"foxglove driver: status {message['message']}", file=sys.stderr)
                if CAMERA in channels and "/lab/drive" in services:
                    known.set()

        reader = asyncio.create_task(receive())
        try:
            await asyncio.wait_for(known.wait(), 10)
            subscription = {"id": camera_sub, "channelId": channels[CAMERA]}
            await ws.send(
                orjson.dumps({"op": "subscribe", "subscriptions": [subscription]}).decode()
            )
            call = orjson.dumps(WHO)
            await ws.send(wire.service_call_request(services["/lab/drive"], 1, "json", call))
            await asyncio.wait_for(answered, 10)
            lags.clear()  # frames of the episode before the drive's
            channel = {
                "id": cmd_vel,
                "topic": "/cmd_vel",
                "encoding": encoding,
                "schemaName": "geometry_msgs/msg/Twist",
            }
            await ws.send(orjson.dumps({"op": "advertise", "channels": [channel]}).decode())

            async def command(z: float) -> None:
                if encoding == "cdr":
                    payload = twist_cdr(z)
                else:
                    payload = orjson.dumps({"angular": {"z": z}} if z else {})
                await ws.send(wire.client_message(cmd_vel, payload))

            return await turns(frames, command, seconds, period, rng), lags
        finally:
            reader.cancel()


VIEWERS = {"rosbridge": "live_viewers.mjs", "foxglove": "live_foxglove_viewers.mjs"}


def phase(
    process: psutil.Process,
    url: str,
    protocol: str,
    viewers: int,
    seconds: float,
    rate: int,
    rng: random.Random,
    encoding: str,
) -> dict[str, Any]:
    """One phase: ``viewers`` of ``protocol`` watching while its driver turns the robot."""
    node = None
    if viewers:
        script = str(ROOT / "bench" / VIEWERS[protocol])
        node = subprocess.Popen(
            ["node", script, url, str(viewers), str(seconds + 4)], stdout=subprocess.PIPE
        )
        assert node.stdout is not None
        assert node.stdout.readline().strip() == b"ready"
    if protocol == "foxglove":
        driver = drive_foxglove(url, seconds, 1 / rate, rng, encoding)
    else:
        driver = drive_rosbridge(url, seconds, 1 / rate, rng)
    cpu_start, wall_start = process.cpu_times(), time.monotonic()
    ((latencies, changes), lags), peak = asyncio.run(watch(driver, process))
    cpu_end, wall = process.cpu_times(), time.monotonic() - wall_start
    seen: dict[str, Any] = {"fps": []}
    if node is not None:
        out, _ = node.communicate(timeout=60)
        seen = json.loads(out.decode().strip().splitlines()[-1])
    used = (cpu_end.user + cpu_end.system) - (cpu_start.user + cpu_start.system)
    return {
        "fps": seen["fps"],
        "jpegs": [seen.get("jpegs", 0), seen.get("checked", 0)],
        "errors": seen.get("errors", []),
        "latency_ms": latencies,
        "change_ms": changes,
        "lag_ms": [(lag - min(lags)) * 1000 for lag in lags],  # a new episode: a new clock
        "cpu_s": used,
        "wall_s": wall,
        "rss": peak,
    }


def run(args: argparse.Namespace, data: Path) -> list[dict[str, Any]]:
    """Every phase, round by round, against one robot; the phases' figures summed."""
    phases = {
        "baseline": ("rosbridge", 0),
        "baseline-foxglove": ("foxglove", 0),
        "rosbridge": ("rosbridge", args.viewers),
        "foxglove": ("foxglove", args.foxglove_viewers),
    }
    rounds: dict[str, list[dict[str, Any]]] = {name: [] for name in phases}
    rng = random.Random(args.seed)
    lab, url = start_lab(args.rate, data)
    process = psutil.Process(lab.pid)
    try:
        for i in range(args.rounds):
            order = list(phases)
            if i % 2:  # the other protocol first, in each pair
                order = [order[1], order[0], order[3], order[2]]
            for name in order:
                protocol, viewers = phases[name]
                seconds = args.seconds / args.rounds
                figures = phase(
                    process, url, protocol, viewers, seconds, args.rate, rng, args.foxglove_encoding
                )
                rounds[name].append(figures)
    finally:
        lab.terminate()
        lab.wait(10)
    results = []
    for name, done in rounds.items():
        protocol, viewers = phases[name]
        checked = [sum(r["jpegs"][k] for r in done) for k in (0, 1)]
        results.append(
            {
                "phase": name,
                "protocol": protocol,
                "viewers": viewers,
                "fps": [round(f, 1) for r in done for f in r["fps"]],
                "jpegs": checked,
                "errors": [e for r in done for e in r["errors"]],
                "latency_ms": sorted(v for r in done for v in r["latency_ms"]),
                "change_ms": sorted(v for r in done for v in r["change_ms"]),
                "lag_ms": sorted(v for r in done for v in r["lag_ms"]),
                "cpu": sum(r["cpu_s"] for r in done) / sum(r["wall_s"] for r in done),
                "rss_mb": max(r["rss"] for r in done) / 1e6,
            }
        )
    return results


async def watch(work: Any, process: psutil.Process) -> tuple[Any, int]:
    """Run ``work`` while sampling the server's RSS every 100 ms: its result, the peak."""
    peak = 0
    task = asyncio.ensure_future(work)
    while not task.done():
        peak = max(peak, process.memory_info().rss)
        await asyncio.sleep(0.1)
    return task.result(), peak


def pct(values: list[float], q: float) -> float:
    if not values:
        return float("nan")
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(q * len(ordered)))]


def mean(values: list[float]) -> float:
    return statistics.fmean(values) if values else float("nan")


def fps_line(label: str, result: dict[str, Any], rate: int) -> str:
    fps = result["fps"]
    if not fps:
        return f"{label}: no frames counted"
    return (
        f"{label}: min {min(fps):.1f}, median {statistics.median(fps):.1f}, max {max(fps):.1f}"
        f" (the camera's rate: {rate}); all: {fps}"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--viewers", type=int, default=10, help="rosbridge viewers")
    parser.add_argument("--foxglove-viewers", type=int, default=10)
    parser.add_argument("--seconds", type=float, default=20.0, help="each phase, all rounds")
    parser.add_argument("--rounds", type=int, default=4)
    parser.add_argument("--rate", type=int, default=25, choices=(20, 25, 50))
    parser.add_argument("--foxglove-encoding", default="cdr", choices=("cdr", "json"))
    parser.add_argument("--seed", type=int, default=0, help="the turns' moments")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    data = Path(os.environ.get("TMPDIR", "/tmp")) / f"labd-bench-live-{os.getpid()}"
    results = run(args, data)
    if args.json:
        print(json.dumps(results, indent=2))
    else:
        report(args, results)


def report(args: argparse.Namespace, results: list[dict[str, Any]]) -> None:
    base, base_fox, ros, fox = results
    print(
        f"camera 640x480 at {args.rate} Hz; {args.viewers} roslibjs viewers (Node),"
        f" {args.foxglove_viewers} Foxglove viewers (Node, foxglove.sdk.v1); {args.seconds:g} s"
        f" a phase in {args.rounds} rounds; Foxglove driver publishes {args.foxglove_encoding}"
    )
    print(
        f"{'':24} {'no viewer':>10} {f'{args.viewers} rosbr.':>10} {'ratio':>7}"
        f" {'no v. (fg)':>10} {f'{args.foxglove_viewers} foxgl.':>10} {'fg/rosbr':>8}"
    )
    for label, get in (
        ("latency p50 (ms)", lambda r: pct(r["latency_ms"], 0.5)),
        ("latency p99 (ms)", lambda r: pct(r["latency_ms"], 0.99)),
        ("latency mean (ms)", lambda r: mean(r["latency_ms"])),
        ("first change p50 (ms)", lambda r: pct(r["change_ms"], 0.5)),
        ("first change mean (ms)", lambda r: mean(r["change_ms"])),
        ("frame lag p50 (ms)", lambda r: pct(r["lag_ms"], 0.5)),
        ("frame lag p99 (ms)", lambda r: pct(r["lag_ms"], 0.99)),
        ("server CPU (cores)", lambda r: r["cpu"]),
        ("server peak RSS (MB)", lambda r: r["rss_mb"]),
    ):
        a, b, c, d = get(base), get(ros), get(base_fox), get(fox)
        print(f"{label:24} {a:10.2f} {b:10.2f} {b / a:7.2f} {c:10.2f} {d:10.2f} {d / b:8.2f}")
    print(fps_line("rosbridge frames/s per viewer", ros, args.rate))
    print(fps_line("Foxglove frames/s per viewer", fox, args.rate))
    jpegs, checked = fox["jpegs"]
    print(f"Foxglove frames decoded by the viewers (one in ten): {checked}, JPEG: {jpegs}")
    if fox["errors"]:
        print(f"Foxglove viewers' errors: {fox['errors'][:5]}")
    counts = ", ".join(f"{r['phase']} {len(r['latency_ms'])}" for r in results)
    print(f"latency samples: {counts}")
    moved = pct(fox["latency_ms"], 0.5) / pct(ros["latency_ms"], 0.5)
    changed = pct(fox["change_ms"], 0.5) / pct(ros["change_ms"], 0.5)
    cpu = fox["cpu"] / ros["cpu"]
    print(
        f"Foxglove/rosbridge (the bar: 1.10): latency p50 {moved:.2f} (the phases' scenes differ),"
        f" first change p50 {changed:.2f}, server CPU {cpu:.2f}"
    )


if __name__ == "__main__":
    sys.exit(main())
