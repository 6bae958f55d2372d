"""A live robot's camera to many viewers, and command-to-pixel latency.

``labd serve`` hosts one maze robot (its camera at 640x480) in a child process. Ten
viewers, roslibjs clients in one Node process (``bench/live_viewers.mjs``, npm
``roslib`` 2.x from ``tests/js/node_modules``; ten headless Chromium pages do not fit
on this 2-core machine beside the lab), subscribe to the camera for ``--seconds``;
meanwhile a driver (a rosbridge client in this process) takes control with
``/lab/drive`` and, again and again, waits until the picture is still, commands a turn
on ``/cmd_vel`` and times the first camera frame whose pixels moved: the
command-to-pixel latency (the same path as a key press in the page, minus the
browser's own key handling and drawing, which the page reports as its "latency" UX
event). Measured: frames per second each viewer received, latency p50/p99, the
server's CPU (share of one core) and peak RSS; the baseline is the same with no
viewer. The maze's control rate sets the camera's: 30 Hz is not one (a tick is a
whole number of 2 ms steps), so ``--rate 25`` (default) or 50.

    .venv/bin/python bench/live.py [--viewers 10] [--seconds 20] [--rate 25] [--json]
"""

from __future__ import annotations

import argparse
import asyncio
import base64
import io
import json
import os
import re
import socket
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import orjson
import psutil
import websockets
from PIL import Image

ROOT = Path(__file__).resolve().parents[1]
MOVED = 3.0  # mean absolute difference (0..255) of a 160x120 grey picture: it moved


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


def grey(message: dict[str, Any]) -> np.ndarray:
    image = Image.open(io.BytesIO(base64.b64decode(message["data"])))
    image.draft("L", (160, 120))
    return np.asarray(image.convert("L").resize((160, 120)), dtype=np.float32)


async def drive(url: str, seconds: float) -> list[float]:
    """Command-to-pixel latencies (ms): a turn commanded while the picture is still, to
    the first frame that moved."""
    latencies: list[float] = []
    async with websockets.connect(url, max_size=None) as ws:
        send = lambda m: ws.send(orjson.dumps(m).decode())  # noqa: E731
        await send({"op": "subscribe", "topic": "/camera/image/compressed", "queue_length": 1})
        who = {"session": "bench", "interface": "video", "user": "bench"}
        await send({"op": "call_service", "service": "/lab/drive", "id": "d", "args": who})
        await send({"op": "advertise", "topic": "/cmd_vel", "type": "geometry_msgs/msg/Twist"})
        frames: asyncio.Queue[tuple[float, np.ndarray]] = asyncio.Queue()

        async def receive() -> None:
            async for text in ws:
                message = orjson.loads(text)
                if message.get("topic") == "/camera/image/compressed":
                    frames.put_nowait((time.perf_counter(), grey(message["msg"])))

        reader = asyncio.create_task(receive())
        end = time.monotonic() + seconds
        turn = 2.0
        try:
            while time.monotonic() < end:
                still = await settle(frames)
                turn = -turn
                sent = time.perf_counter()
                await send({"op": "publish", "topic": "/cmd_vel",
                            "msg": {"angular": {"z": turn}}})  # fmt: skip
                while True:
                    arrived, picture = await asyncio.wait_for(frames.get(), 5)
                    if float(np.abs(picture - still).mean()) > MOVED:
                        latencies.append((arrived - sent) * 1000)
                        break
                    if arrived - sent > 0.2:  # keep the turn going, as a held key does
                        await send({"op": "publish", "topic": "/cmd_vel",
                                    "msg": {"angular": {"z": turn}}})  # fmt: skip
                await send({"op": "publish", "topic": "/cmd_vel", "msg": {}})
        finally:
            reader.cancel()
    return latencies


async def settle(frames: asyncio.Queue[tuple[float, np.ndarray]]) -> np.ndarray:
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


def run(viewers: int, seconds: float, rate: int, data: Path) -> dict[str, Any]:
    lab, url = start_lab(rate, data)
    process = psutil.Process(lab.pid)
    try:
        node = None
        if viewers:
            script = str(ROOT / "bench" / "live_viewers.mjs")
            node = subprocess.Popen(
                ["node", script, url, str(viewers), str(seconds + 4)], stdout=subprocess.PIPE
            )
            assert node.stdout is not None
            assert node.stdout.readline().strip() == b"ready"
        cpu_start, wall_start = process.cpu_times(), time.monotonic()
        latencies, peak = asyncio.run(watch(drive(url, seconds), process))
        cpu_end, wall = process.cpu_times(), time.monotonic() - wall_start
        fps: list[float] = []
        if node is not None:
            out, _ = node.communicate(timeout=60)
            fps = json.loads(out.decode().strip().splitlines()[-1])["fps"]
        used = (cpu_end.user + cpu_end.system) - (cpu_start.user + cpu_start.system)
        return {
            "viewers": viewers,
            "fps": [round(f, 1) for f in fps],
            "latency_ms": sorted(latencies),
            "cpu": used / wall,
            "rss_mb": peak / 1e6,
        }
    finally:
        lab.terminate()
        lab.wait(10)


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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--viewers", type=int, default=10)
    parser.add_argument("--seconds", type=float, default=20.0)
    parser.add_argument("--rate", type=int, default=25, choices=(20, 25, 50))
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    data = Path(os.environ.get("TMPDIR", "/tmp")) / f"labd-bench-live-{os.getpid()}"
    results = [run(n, args.seconds, args.rate, data) for n in (0, args.viewers)]
    if args.json:
        print(json.dumps(results, indent=2))
        return
    base, loaded = results
    print(
        f"camera 640x480 at {args.rate} Hz; {args.viewers} roslibjs viewers (Node),"
        f" {args.seconds:g} s"
    )
    print(f"{'':32} {'no viewer':>12} {f'{args.viewers} viewers':>12} {'ratio':>7}")
    for label, a, b in (
        ("latency p50 (ms)", pct(base["latency_ms"], 0.5), pct(loaded["latency_ms"], 0.5)),
        ("latency p99 (ms)", pct(base["latency_ms"], 0.99), pct(loaded["latency_ms"], 0.99)),
        ("server CPU (cores)", base["cpu"], loaded["cpu"]),
        ("server peak RSS (MB)", base["rss_mb"], loaded["rss_mb"]),
    ):
        print(f"{label:32} {a:12.2f} {b:12.2f} {b / a:7.2f}")
    fps = loaded["fps"]
    print(f"frames/s per viewer: min {min(fps):.1f}, median {statistics.median(fps):.1f}, "
          f"max {max(fps):.1f} (the camera's rate: {args.rate}); all: {fps}")  # fmt: skip
    print(f"latency samples: {len(base['latency_ms'])} and {len(loaded['latency_ms'])}")


if __name__ == "__main__":
    sys.exit(main())
