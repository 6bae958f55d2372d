"""How fast the simulated robots run: in-process against through the bridge, and the camera.

For each task, in one run:

- **in-process**: a scripted policy steps the dm_control environment directly
  (``env.step(action)``), as an RL agent in the same process would;
- **bridge**: the same policy, in a separate process, drives the same task through
  ``labd serve --lockstep`` over rosbridge: each tick it publishes its command, calls
  ``/lab/step``, and reads the observations it needs from the topics;

and prints control ticks per second of each, the ratio, and how much faster than real
time the bridge-driven loop runs. Then the live camera: a client subscribed to
``/camera/image/compressed`` of a live ``icreate-maze`` robot at 320x240 counts the
frames it receives per second.

Targets (from the issue): the bridge-driven loop at least 50% of the in-process one for
``icreate-maze`` without camera, and at least 20 times faster than real time; the live
camera at least 15 frames per second.

    .venv/bin/python bench/sim.py [--ticks N] [--camera-seconds S] [--json]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import os
import re
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import orjson
import websockets

from controllers.client import Lab
from labd.sim.simulation import Simulation

ROOT = Path(__file__).resolve().parent.parent

BRIDGE_RATIO = 0.50  # bridge ticks/s over in-process ticks/s, icreate-maze, at least
REAL_TIME = 20.0  # bridge-driven simulated seconds per wall second, at least
CAMERA_FPS = 15.0  # live camera frames per second at 320x240, at least


# -- the policies: the same decisions from in-process observations and from topics ------


def maze_policy(
    bumped: bool, goal_x: float, goal_y: float, turning: int
) -> tuple[float, float, int]:
    """Head for the goal; after a bump, back off and turn for a few ticks."""
    if bumped:
        return -0.1, 2.0, 8
    if turning > 0:
        return 0.0, 2.0, turning - 1
    heading = math.atan2(goal_y, goal_x)
    return 0.3 * max(0.0, math.cos(heading)), max(-2.0, min(2.0, 2.0 * heading)), 0


def maze_from_topics(
    bumper: dict[str, Any], odom: dict[str, Any], goal: dict[str, Any], turning: int
) -> tuple[float, float, int]:
    """``maze_policy`` fed from the topics' messages: the goal in the robot's frame."""
    pose = odom["pose"]["pose"]
    yaw = 2 * math.atan2(pose["orientation"]["z"], pose["orientation"]["w"])
    dx = goal["point"]["x"] - pose["position"]["x"]
    dy = goal["point"]["y"] - pose["position"]["y"]
    gx = math.cos(yaw) * dx + math.sin(yaw) * dy
    gy = -math.sin(yaw) * dx + math.cos(yaw) * dy
    return maze_policy(bumper["left"] or bumper["right"], gx, gy, turning)


def pr2_policy(tick: int) -> tuple[float, float, float]:
    """Sway the base and the torso: exercises the whole model every tick."""
    return 0.2 * math.sin(tick / 10), 0.1 * math.cos(tick / 13), 0.15 + 0.1 * math.sin(tick / 20)


def in_process(task: str, ticks: int) -> dict[str, float]:
    """Ticks per second of the policy stepping dm_control directly."""
    sim = Simulation(task, {"time_limit": 3600.0}, seed=1)
    env, physics = sim.env, sim.physics
    timestep = env.reset()
    turning = 0
    started = time.perf_counter()
    for tick in range(ticks):
        obs = timestep.observation
        if task == "icreate-maze":
            linear, angular, turning = maze_policy(
                bool(obs["bumpers"].any()), *obs["goal"], turning
            )
            sim.task.command(
                "/cmd_vel",
                {
                    "linear": {"x": linear, "y": 0.0, "z": 0.0},
                    "angular": {"x": 0.0, "y": 0.0, "z": angular},
                },
            )
        else:
            vx, wz, _ = pr2_policy(tick)
            sim.task.command(
                "/base/cmd_vel",
                {"linear": {"x": vx, "y": 0.0, "z": 0.0}, "angular": {"x": 0.0, "y": 0.0, "z": wz}},
            )
        timestep = env.step(sim.task.action(physics))
        if timestep.last():
            timestep = env.reset()
    elapsed = time.perf_counter() - started
    return {"ticks_per_s": ticks / elapsed, "control_timestep": sim.control_timestep}


# -- the bridge-driven client (runs in its own process) ---------------------------------------


async def drive_over_bridge(url: str, task: str, ticks: int) -> dict[str, float]:
    """The policy as a rosbridge client in lockstep; returns ticks per second."""
    async with websockets.connect(url, max_size=None, compression=None) as ws:

        async def send(frame: dict[str, Any]) -> None:
            await ws.send(orjson.dumps(frame).decode())

        if task == "icreate-maze":
            inputs = {
                "/bumper": "lab_msgs/msg/Bumper",
                "/odom": "nav_msgs/msg/Odometry",
                "/goal": "geometry_msgs/msg/PointStamped",
            }
            command = ("/cmd_vel", "geometry_msgs/msg/Twist")
        else:
            inputs = {"/joint_states": "sensor_msgs/msg/JointState"}
            command = ("/base/cmd_vel", "geometry_msgs/msg/Twist")
        latest: dict[str, Any] = {}
        for topic, type_name in inputs.items():
            await send({"op": "subscribe", "topic": topic, "type": type_name})
        await send({"op": "advertise", "topic": command[0], "type": command[1]})

        async def step(tick: int) -> None:
            await send({"op": "call_service", "id": f"s{tick}", "service": "/lab/step"})
            while True:
                frame = orjson.loads(await ws.recv())
                if frame["op"] == "publish":
                    latest[frame["topic"]] = frame["msg"]
                elif frame.get("id") == f"s{tick}":
                    if not frame["values"]["success"]:
                        raise RuntimeError(frame["values"]["message"])
                    return

        await step(-1)  # the first tick also collects the latched state
        turning = 0
        started = time.perf_counter()
        for tick in range(ticks):
            if task == "icreate-maze":
                linear, angular, turning = maze_from_topics(
                    latest["/bumper"], latest["/odom"], latest["/goal"], turning
                )
            else:
                linear, angular, _ = pr2_policy(tick)
            await send(
                {
                    "op": "publish",
                    "topic": command[0],
                    "msg": {"linear": {"x": linear}, "angular": {"z": angular}},
                }
            )
            await step(tick)
        elapsed = time.perf_counter() - started
    return {"ticks_per_s": ticks / elapsed}


def drive_with_client_library(url: str, task: str, ticks: int) -> dict[str, float]:
    """The same policy through the lab's own client library (``controllers.client``):
    a blocking socket read on the caller's thread, a tick's commands sent with its
    ``/lab/step`` in one write."""
    with Lab.connect(url) as lab:
        if task == "icreate-maze":
            bumper = lab.subscribe("/bumper", "lab_msgs/msg/Bumper")
            odom = lab.subscribe("/odom", "nav_msgs/msg/Odometry")
            goal = lab.subscribe("/goal", "geometry_msgs/msg/PointStamped")
            command = ("/cmd_vel", "geometry_msgs/msg/Twist")
        else:
            lab.subscribe("/joint_states", "sensor_msgs/msg/JointState")
            command = ("/base/cmd_vel", "geometry_msgs/msg/Twist")
        lab.step()  # the first tick also collects the latched state
        turning = 0
        started = time.perf_counter()
        for tick in range(ticks):
            if task == "icreate-maze":
                linear, angular, turning = maze_from_topics(
                    bumper.get(), odom.get(), goal.get(), turning
                )
            else:
                linear, angular, _ = pr2_policy(tick)
            lab.publish(
                command[0], command[1], {"linear": {"x": linear}, "angular": {"z": angular}}
            )
            lab.step()
        elapsed = time.perf_counter() - started
    return {"ticks_per_s": ticks / elapsed}


async def count_camera_frames(url: str, seconds: float) -> dict[str, float]:
    """Frames per second a subscriber receives from a live robot's camera."""
    async with websockets.connect(url, max_size=None, compression=None) as ws:
        await ws.send(
            orjson.dumps(
                {
                    "op": "subscribe",
                    "topic": "/camera/image/compressed",
                    "type": "sensor_msgs/msg/CompressedImage",
                }
            ).decode()
        )
        stamps = set()
        await ws.recv()  # the first (maybe latched) frame starts the clock
        started = time.perf_counter()
        size = 0
        while (elapsed := time.perf_counter() - started) < seconds:
            try:
                frame = orjson.loads(await asyncio.wait_for(ws.recv(), seconds - elapsed))
            except TimeoutError:
                break
            stamp = frame["msg"]["header"]["stamp"]
            stamps.add((stamp["sec"], stamp["nanosec"]))
            size = len(frame["msg"]["data"])
    return {"fps": len(stamps) / seconds, "jpeg_base64_bytes": size}


def client_main(argv: list[str]) -> None:
    mode, url, task, amount = argv
    if mode == "drive":
        result = asyncio.run(drive_over_bridge(url, task, int(amount)))
    elif mode == "library":
        result = drive_with_client_library(url, task, int(amount))
    else:
        result = asyncio.run(count_camera_frames(url, float(amount)))
    print(json.dumps(result))


# -- orchestration -----------------------------------------------------------------------------


class Server:
    """``labd serve`` in its own process, on free ports, running no trials."""

    def __init__(self, *args: str) -> None:
        self.proc = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "labd",
                "serve",
                "--bridge-port",
                "0",
                "--http-port",
                "0",
                "--workers",
                "0",
                "--videos",
                "asked",
                "--no-playground",
                *args,
            ],
            cwd=ROOT,
            stdout=subprocess.PIPE,
            stderr=subprocess.DEVNULL,
            text=True,
        )
        assert self.proc.stdout is not None
        line = self.proc.stdout.readline()
        match = re.search(r"on (ws://\S+)", line)
        if not match:
            self.close()
            raise RuntimeError(f"labd serve did not start: {line!r}")
        self.url = match.group(1)

    def close(self) -> None:
        self.proc.terminate()
        try:
            self.proc.wait(10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()

    def __enter__(self) -> Server:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def client(mode: str, url: str, task: str, amount: float) -> dict[str, float]:
    out = subprocess.run(
        [sys.executable, __file__, "--client", mode, url, task, str(amount)],
        cwd=ROOT,
        check=True,
        capture_output=True,
        text=True,
        timeout=600,
    )
    result: dict[str, float] = json.loads(out.stdout)
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--ticks", type=int, default=2000, help="control ticks per measurement")
    parser.add_argument("--camera-seconds", type=float, default=10.0)
    parser.add_argument("--tasks", default="icreate-maze,pr2-table")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--client", nargs=4, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.client:
        client_main(args.client)
        return
    results: dict[str, Any] = {"tasks": {}}
    for task in args.tasks.split(","):
        print(f"[bench] {task}: in-process", file=sys.stderr)
        local = in_process(task, args.ticks)
        print(f"[bench] {task}: through the bridge", file=sys.stderr)
        with Server("--robot", f"bench={task}", "--lockstep", "--param", "time_limit=3600") as srv:
            remote = client("drive", srv.url, task, args.ticks)
        print(f"[bench] {task}: through the bridge, the lab's client library", file=sys.stderr)
        with Server("--robot", f"bench={task}", "--lockstep", "--param", "time_limit=3600") as srv:
            library = client("library", srv.url, task, args.ticks)
        dt = local["control_timestep"]
        results["tasks"][task] = {
            "in_process_ticks_per_s": local["ticks_per_s"],
            "bridge_ticks_per_s": remote["ticks_per_s"],
            "ratio": remote["ticks_per_s"] / local["ticks_per_s"],
            "library_ticks_per_s": library["ticks_per_s"],
            "library_ratio": library["ticks_per_s"] / local["ticks_per_s"],
            "control_timestep": dt,
            "bridge_real_time_factor": remote["ticks_per_s"] * dt,
            "in_process_real_time_factor": local["ticks_per_s"] * dt,
        }
    print("[bench] live camera", file=sys.stderr)
    with Server("--robot", "cam=icreate-maze") as srv:
        results["camera"] = client("camera", srv.url, "icreate-maze", args.camera_seconds)
    maze = results["tasks"].get("icreate-maze")
    results["targets"] = {
        "bridge_ratio_icreate": bool(maze and maze["ratio"] >= BRIDGE_RATIO),
        "real_time_icreate": bool(maze and maze["bridge_real_time_factor"] >= REAL_TIME),
        "camera_fps": results["camera"]["fps"] >= CAMERA_FPS,
    }
    if args.json:
        print(json.dumps(results, indent=2))
        return
    report(results, args)


def report(results: dict[str, Any], args: argparse.Namespace) -> None:
    print(
        "Simulated robots: a scripted policy in-process against the same policy through the "
        "bridge (lockstep, separate process)"
    )
    print(
        f"  {args.ticks} control ticks each; {os.cpu_count()} CPUs; MUJOCO_GL="
        f"{os.environ.get('MUJOCO_GL')}\n"
    )
    print(
        f"  {'task':14} {'in-process':>12} {'bridge':>12} {'ratio':>7} {'x real time':>12}"
        f" {'library':>12} {'ratio':>7}"
    )
    for task, r in results["tasks"].items():
        print(
            f"  {task:14} {r['in_process_ticks_per_s']:9,.0f}/s {r['bridge_ticks_per_s']:9,.0f}/s"
            f" {r['ratio']:7.2f} {r['bridge_real_time_factor']:11.0f}x"
            f" {r['library_ticks_per_s']:9,.0f}/s {r['library_ratio']:7.2f}"
            f"   (control period {r['control_timestep'] * 1000:.0f} ms)"
        )
    print(
        "  bridge: a raw asyncio rosbridge client (websockets, one write a frame); library:"
        " the lab's client library (controllers.client)"
    )
    cam = results["camera"]
    print(
        f"\n  live camera, 320x240 JPEG: {cam['fps']:.1f} frames/s received "
        f"({cam['jpeg_base64_bytes'] / 1000:.0f} kB a frame as base64)\n"
    )
    marks = {True: "PASS", False: "FAIL"}
    t = results["targets"]
    print(f"  {marks[t['bridge_ratio_icreate']]}  icreate-maze bridge/in-process >= {BRIDGE_RATIO}")
    print(
        f"  {marks[t['real_time_icreate']]}  icreate-maze through the bridge >= {REAL_TIME:g}x "
        "real time"
    )
    print(f"  {marks[t['camera_fps']]}  live camera >= {CAMERA_FPS:g} frames/s")


if __name__ == "__main__":
    main()
