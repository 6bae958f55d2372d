"""The simulated robots behind a real bridge, driven by the real clients."""

from __future__ import annotations

import base64
import io
import json
import subprocess
import threading
from pathlib import Path

import pytest
import roslibpy
from PIL import Image
from websockets.sync.client import connect

from labd.config import BridgeConfig, RobotConfig

pytestmark = pytest.mark.integration
JS = Path(__file__).resolve().parents[1] / "js"
WAIT = 20.0


@pytest.fixture
def lockstep_maze(make_server):
    return make_server(
        BridgeConfig(port=0), robots=(RobotConfig("maze", "icreate-maze", seed=3, live=False),)
    )


@pytest.fixture
def ros(lockstep_maze):
    client = roslibpy.Ros(host="127.0.0.1", port=lockstep_maze.port)
    client.run(timeout=WAIT)
    yield client
    client.close()


def test_roslibpy_drives_the_maze_in_lockstep(ros):
    """Commanding 0.2 m/s forward for ten ticks of /lab/step moves /odom about 0.2 m forward."""
    poses = []
    arrived = threading.Condition()

    def on_odom(message):
        with arrived:
            poses.append(message["pose"]["pose"]["position"])
            arrived.notify_all()

    roslibpy.Topic(ros, "/odom", "nav_msgs/msg/Odometry").subscribe(on_odom)
    with arrived:
        assert arrived.wait_for(lambda: poses, WAIT)  # latched: the pose at tick 0
    start = dict(poses[-1])
    cmd = roslibpy.Topic(ros, "/cmd_vel", "geometry_msgs/msg/Twist")
    step = roslibpy.Service(ros, "/lab/step", "std_srvs/srv/Trigger")
    for tick in range(1, 11):
        cmd.publish(roslibpy.Message({"linear": {"x": 0.2}}))
        answer = step.call(roslibpy.ServiceRequest(), timeout=WAIT)
        assert answer["success"] is True and answer["message"].startswith(f"tick {tick} ")
    with arrived:
        assert arrived.wait_for(lambda: len(poses) >= 11, WAIT)
    moved = poses[-1]["x"] - start["x"]
    assert 0.12 < moved < 0.24, poses[-1]
    assert abs(poses[-1]["y"] - start["y"]) < 0.02


def test_roslibpy_gets_ticks_in_order_before_each_answer(ros):
    """Each step's /clock arrives before that step's answer: observations come first."""
    order = []
    lock = threading.Lock()
    roslibpy.Topic(ros, "/clock", "rosgraph_msgs/msg/Clock").subscribe(
        lambda m: order.append(("clock", m["clock"]["nanosec"]))
    )
    step = roslibpy.Service(ros, "/lab/step", "std_srvs/srv/Trigger")
    ros.get_time()  # round trip: the subscription is in place
    for _ in range(3):
        step.call(roslibpy.ServiceRequest(), timeout=WAIT)
        with lock:
            order.append(("answer", None))
    clocks = [i for i, (kind, _) in enumerate(order) if kind == "clock"]
    answers = [i for i, (kind, _) in enumerate(order) if kind == "answer"]
    assert len(clocks) == 3, order  # /clock is not latched: one per tick
    assert all(clocks[k] < answers[k] for k in range(3)), order
    assert [nanosec for kind, nanosec in order if kind == "clock"] == [
        100_000_000,
        200_000_000,
        300_000_000,
    ]


@pytest.fixture
def live_maze(make_server):
    return make_server(BridgeConfig(port=0), robots=(RobotConfig("icreate-1", "icreate-maze"),))


def test_roslibjs_receives_live_camera_frames(live_maze):
    """roslibjs subscribed to the live robot's camera receives frames that decode as JPEG."""
    url = live_maze.url + "/robots/icreate-1"
    result = subprocess.run(
        ["node", str(JS / "camera.mjs"), url, "3"],
        cwd=JS,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert result.returncode == 0, result.stderr
    frames = json.loads(result.stdout)["frames"]
    assert len(frames) == 3
    stamps = [f["stamp"] for f in frames]
    assert stamps == sorted(stamps) and len(set(stamps)) == 3
    for frame in frames:
        assert frame["format"] == "jpeg"
        with Image.open(io.BytesIO(base64.b64decode(frame["data"]))) as image:
            assert image.format == "JPEG" and image.size == (320, 240)


def test_a_client_cannot_publish_the_live_robots_odometry(live_maze):
    """On a live robot, roslibpy publishing /odom (x = 42) is refused, the lab's log names the
    topic, another roslibpy subscriber never receives it; a raw client gets the status."""
    url = live_maze.url + "/robots/icreate-1"
    graph = live_maze.lab.graphs["icreate-1"]
    watcher = roslibpy.Ros(host=url)
    forger = roslibpy.Ros(host=url)
    watcher.run(timeout=WAIT)
    forger.run(timeout=WAIT)
    seen, log = [], []
    arrived = threading.Condition()

    def keep(into):
        def take(message):
            with arrived:
                into.append(message)
                arrived.notify_all()

        return take

    try:
        roslibpy.Topic(watcher, "/odom", "nav_msgs/msg/Odometry").subscribe(keep(seen))
        roslibpy.Topic(watcher, "/rosout", "rcl_interfaces/msg/Log").subscribe(keep(log))
        live_maze.wait_until(
            lambda: (
                "/rosout" in graph.topics
                and len(graph.topics["/odom"].subscriptions) == 1
                and len(graph.topics["/rosout"].subscriptions) == 1
            )
        )
        forged = roslibpy.Topic(forger, "/odom", "nav_msgs/msg/Odometry")
        for _ in range(3):
            forged.publish(roslibpy.Message({"pose": {"pose": {"position": {"x": 42.0}}}}))
        after = forger.get_time()  # a round trip: the publishes before it have been handled
        after_ns = after.secs * 10**9 + after.nsecs

        def stamp(message):
            return message["header"]["stamp"]["sec"] * 10**9 + message["header"]["stamp"]["nanosec"]

        def refusals():
            return [m["msg"] for m in log if "/odom belongs to the lab" in m["msg"]]

        with arrived:
            assert arrived.wait_for(lambda: any(stamp(m) > after_ns for m in seen), WAIT)
            assert arrived.wait_for(lambda: len(refusals()) == 4, WAIT), (
                log
            )  # advertise, 3 publishes
        assert all(m["pose"]["pose"]["position"]["x"] != 42.0 for m in seen)
        assert [p.node.name for p in graph.topics["/odom"].publishers] == ["/icreate_1"]
    finally:
        watcher.close()
        forger.close()

    with connect(url) as raw:
        raw.send(json.dumps({"op": "set_level", "level": "error"}))
        raw.send(json.dumps({"op": "publish", "topic": "/odom", "msg": {}, "id": "forge"}))
        status = json.loads(raw.recv(timeout=WAIT))
    assert status == {
        "op": "status",
        "level": "error",
        "msg": "publish: topic /odom belongs to the lab (/icreate_1 publishes it); "
        "clients cannot advertise or publish on it",
        "id": "forge",
    }
