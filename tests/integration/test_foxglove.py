"""Foxglove's own client (npm ``@foxglove/ws-protocol`` 0.8, unmodified, run by Node.js)
at a live robot's URL, beside roslibjs on the same port.

Each test runs scenarios of ``tests/js/foxglove.mjs`` against a real lab with the live
maze robot: the script drives FoxgloveClients, decodes what they receive with
Foxglove's ROS 2 reader (``@foxglove/rosmsg2-serialization``) and prints what it
observed as JSON; the assertions are here (``harness.mjs`` describes the contract).
"""

from __future__ import annotations

import asyncio
import itertools
import json
import os
import shutil
import socket
import struct
import subprocess
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from websockets.asyncio.client import connect as ws_connect
from websockets.exceptions import InvalidStatus
from websockets.typing import Subprotocol

from labd.bridge.auth import AuthError, Grant
from labd.bridge.foxglove.session import Channels, FoxgloveSession
from labd.config import BridgeConfig
from repository.index import Filters
from repository.trial import Kind
from tests.helpers.labs import MAZE, ServerThread, lab_config, running

JS = Path(__file__).resolve().parents[1] / "js"
NODE = shutil.which("node")
TIMEOUT = 60  # seconds for one script; its own waits are bounded far below this
ROBOT = MAZE.name

pytestmark = [
    pytest.mark.integration,
    pytest.mark.timeout(180),
    pytest.mark.skipif(NODE is None, reason="Node.js (node, version 20 or later) is not installed"),
]


def foxglove(
    url: str, *scenarios: str, offered: str = "foxglove.sdk.v1", key: str = ""
) -> dict[str, Any]:
    """Run ``scenarios`` of ``tests/js/foxglove.mjs`` at ``url``, offering the
    subprotocols ``offered``; their observations by name."""
    if not (JS / "node_modules" / "@foxglove" / "ws-protocol").is_dir():
        pytest.fail(f"{JS / 'node_modules'} has no @foxglove/ws-protocol: run `make setup`")
    assert NODE is not None
    env = {**os.environ, "FOXGLOVE_SUBPROTOCOLS": offered, "FOXGLOVE_KEY": key}
    proc = subprocess.run(
        [NODE, str(JS / "foxglove.mjs"), url, *scenarios],
        cwd=JS,
        capture_output=True,
        text=True,
        timeout=TIMEOUT,
        check=False,
        env=env,
    )
    assert proc.returncode == 0, (
        f"foxglove.mjs {scenarios} exited {proc.returncode}:\n{proc.stderr}"
    )
    observed: dict[str, Any] = json.loads(proc.stdout)["scenarios"]
    return observed


@pytest.fixture(scope="module")
def maze_server(tmp_path_factory: pytest.TempPathFactory) -> Any:
    """A lab with the live maze robot and the archive, no worker."""
    with running(lab_config(tmp_path_factory.mktemp("foxglove") / "data")) as server:
        yield server


def robot_url(server: ServerThread) -> str:
    return f"{server.url}/robots/{ROBOT}"


@pytest.mark.parametrize(
    "offered",
    ["foxglove.sdk.v1", "foxglove.websocket.v1", "foxglove.websocket.v1,foxglove.sdk.v1"],
    ids=["sdk", "websocket", "both-as-lichtblick-offers"],
)
def test_a_foxglove_client_gets_server_info_and_every_topic_as_a_ros2_channel(maze_server, offered):
    """Whichever of Foxglove's names the client offers, it is answered in that protocol
    (the SDK's name when it offers both); ``serverInfo`` lists the capabilities the lab
    has, and every topic of the robot is a channel in CDR with its ROS 2 definition,
    which Foxglove's own parser reads."""
    seen = foxglove(robot_url(maze_server), "connect", offered=offered)["connect"]
    expected = "foxglove.sdk.v1" if "foxglove.sdk.v1" in offered else "foxglove.websocket.v1"
    assert seen["protocol"] == expected
    info = seen["info"]
    assert sorted(info["capabilities"]) == sorted(
        ["clientPublish", "services", "parameters", "time", "connectionGraph"]
    )
    assert info["supportedEncodings"] == ["cdr", "json"]
    assert info["metadata"] == {"ROS_DISTRO": "jazzy", "robot": ROBOT}
    channels = {c["topic"]: c for c in seen["channels"]}
    for topic in ("/odom", "/tf", "/camera/image/compressed", "/cmd_vel", "/lab/episode"):
        assert topic in channels, sorted(channels)
    assert channels["/camera/image/compressed"]["schemaName"] == "sensor_msgs/msg/CompressedImage"
    assert {(c["encoding"], c["schemaEncoding"]) for c in seen["channels"]} == {("cdr", "ros2msg")}
    assert all(ok is True for ok in seen["parsed"]), seen["parsed"]
    services = {s["name"]: s for s in seen["services"]}
    assert {"/lab/reset", "/lab/drive", "/lab/release", "/rosapi/topics"} <= services.keys()
    assert services["/lab/reset"]["request"] == {
        "encoding": "cdr",
        "schemaName": "std_srvs/srv/Trigger_Request",
        "schemaEncoding": "ros2msg",
    }


def test_odometry_decodes_with_foxglove_s_ros2_reader_in_simulation_time(maze_server):
    """/odom arrives as CDR that Foxglove's reader decodes whole (no trailing bytes),
    each message stamped with the simulation time of its tick, which a Time frame
    announced before it."""
    seen = foxglove(robot_url(maze_server), "odom")["odom"]
    assert seen["channel"]["schemaName"] == "nav_msgs/msg/Odometry"
    messages = seen["messages"]
    assert len(messages) == 5
    for item in messages:
        odom = item["message"]
        assert item["trailing"] is False
        assert odom["header"]["frame_id"] == "odom"
        assert odom["child_frame_id"] == "base_link"
        assert odom["pose"]["pose"]["orientation"]["w"] == pytest.approx(1.0, abs=0.1)
        stamp = odom["header"]["stamp"]
        assert int(item["timestamp"]) == stamp["sec"] * 10**9 + stamp["nanosec"]
        assert item["timestamp"] in seen["times"]  # announced by a Time frame
    stamps = [int(item["timestamp"]) for item in messages]
    assert stamps == sorted(stamps) and len(set(stamps)) == 5  # one a tick, in order


def test_teleop_drives_with_cdr_and_json_and_the_drive_is_a_demonstration(maze_server):
    """A client publishing /cmd_vel (CDR, then JSON) drives the robot: it turns, then
    moves; /lab/driver names it, with the interface "foxglove"; a second client that
    publishes is refused in a status and does not drive. When the driver leaves, its
    drive is filed as a demonstration under the foxglove interface."""
    service = maze_server.lab.service
    before = len(service.index.find(Filters(kind=Kind.DEMONSTRATION)).items)
    seen = foxglove(robot_url(maze_server), "drive")["drive"]
    assert seen["turned"] and seen["moved"]
    assert seen["refused"]["level"] == 1
    assert f"{ROBOT} is driven by guest:client_" in seen["refused"]["message"]
    assert "you are watching" in seen["refused"]["message"]
    assert seen["refused"]["id"] == "/cmd_vel"  # one status, replaced at each refusal
    assert seen["driverStatuses"] == []
    driving = [d for d in seen["drivers"] if d["driver"]]
    assert driving and driving[-1]["interface"] == "foxglove"
    deadline = time.monotonic() + 30
    while len(found := service.index.find(Filters(kind=Kind.DEMONSTRATION)).items) == before:
        assert time.monotonic() < deadline, "no demonstration filed"
        time.sleep(0.1)
    demo = found[0]
    assert demo.manifest["driver"]["interface"] == "foxglove"
    assert demo.submitter == driving[-1]["driver"]


def test_services_answer_in_the_encoding_they_were_called_in(maze_server):
    """/lab/reset called in CDR is answered in CDR (Foxglove's reader decodes it), in
    JSON in JSON; rosapi answers too; a call of no service, or with bytes that are no
    request, fails saying why."""
    seen = foxglove(robot_url(maze_server), "services")["services"]
    assert seen["requestHex"] == "0001000000"  # an empty request, as ROS 2 writes it
    assert seen["cdr"]["encoding"] == "cdr"
    assert seen["cdr"]["value"]["success"] is True
    assert seen["cdr"]["value"]["message"].startswith("new episode, seed ")
    assert seen["json"]["encoding"] == "json"
    assert seen["json"]["value"]["success"] is True
    assert "/odom" in seen["topics"]["topics"]
    failures = {f["callId"]: f["message"] for f in seen["failures"]}
    assert failures[4] == "no service with id 9999"
    assert failures[5].startswith(
        "/lab/reset: the bytes are not a CDR std_srvs/srv/Trigger_Request"
    )


def test_parameters_are_the_robot_s_and_read_only(maze_server):
    """getParameters gives the task's parameters, all or those named; setParameters is
    refused in an error status and answered with the values unchanged."""
    seen = foxglove(robot_url(maze_server), "params")["params"]
    everything, some, after_set = seen["values"]
    values = {p["name"]: p["value"] for p in everything["parameters"]}
    assert values["camera_width"] == 320 and values["maze_size"] == 9
    assert everything["id"] == "all"
    assert some == {
        "op": "parameterValues",
        "parameters": [{"name": "camera_width", "value": 320}],
        "id": "some",
    }
    assert after_set["parameters"] == [{"name": "camera_width", "value": 320}]
    assert seen["status"]["level"] == 2 and "read-only" in seen["status"]["message"]


def test_the_connection_graph_and_its_changes(maze_server):
    """The first update holds who publishes and provides what; the client's own
    subscription to /odom comes in a later one."""
    seen = foxglove(robot_url(maze_server), "graph")["graph"]
    published = {t["name"]: t["publisherIds"] for t in seen["first"]["publishedTopics"]}
    assert published["/odom"] == [f"/{ROBOT.replace('-', '_')}"]
    services = {s["name"] for s in seen["first"]["advertisedServices"]}
    assert "/lab/reset" in services
    later = [t for u in seen["later"] for t in u["subscribedTopics"] if t["name"] == "/odom"]
    assert any(any(n.startswith("/bridge/client_") for n in t["subscriberIds"]) for t in later)


def test_the_camera_streams_jpeg_while_subscribed_beside_roslibjs(maze_server):
    """A Foxglove client and a roslibjs client watch the camera at the same time on the
    same port; Foxglove's frames are JPEGs in sensor_msgs/msg/CompressedImage, and none
    come once it unsubscribes."""
    assert NODE is not None
    roslibjs = subprocess.Popen(
        [NODE, str(JS / "camera.mjs"), robot_url(maze_server), "3"],
        cwd=JS,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        seen = foxglove(robot_url(maze_server), "camera")["camera"]
        out, err = roslibjs.communicate(timeout=TIMEOUT)
    finally:
        roslibjs.kill()
    assert roslibjs.returncode == 0, err
    assert len(json.loads(out)["frames"]) == 3
    assert [f["format"] for f in seen["frames"]] == ["jpeg"] * 3
    assert all(f["head"] == "ffd8ff" and not f["trailing"] for f in seen["frames"])
    assert seen["afterUnsubscribe"] == 0


class Keys:
    """An authorizer that knows one key, alice's."""

    async def authorize(self, key: str, graph: str) -> Grant:
        if key != "alice-key":
            raise AuthError("the key is not known")
        return Grant(60.0, user="alice")


def test_a_key_in_the_url_opens_the_robot_and_a_wrong_one_is_refused(tmp_path):
    """On a robot that needs a key, the key goes in the URL (the protocol has no place
    for one): the right one opens it to Foxglove's client; a wrong one is refused in an
    error status, and the connection closes."""
    config = lab_config(tmp_path / "data", bridge=BridgeConfig(port=0, auth_timeout=5))
    server = ServerThread(config, authorizer=Keys()).start()
    try:
        url = robot_url(server)
        opened = foxglove(url, "keyed", key="alice-key")["keyed"]
        refused = foxglove(url, "keyed", key="mallory-key")["keyed"]
    finally:
        server.stop()
    assert opened["channels"] > 5 and opened["statuses"] == []
    assert opened["closed"] is None
    assert refused["channels"] == 0
    assert refused["statuses"] == [
        {"op": "status", "level": 2, "message": "authorization refused: the key is not known"}
    ]
    assert refused["closed"] == 1008


LAYOUT = (
    Path(__file__).resolve().parents[2] / "docs" / "examples" / "foxglove" / "icreate-maze.json"
)


def test_the_maze_layout_names_only_what_the_robot_has(maze_server):
    """docs/examples/foxglove/icreate-maze.json (docs/live.md) shows topics the maze
    robot publishes and drives the one it obeys, often enough to outrun the watchdog."""
    layout = json.loads(LAYOUT.read_text())
    panels = layout["configById"]
    named: set[str] = set()

    def leaves(node: Any) -> set[str]:
        if isinstance(node, str):
            return {node}
        return leaves(node["first"]) | leaves(node["second"])

    assert leaves(layout["layout"]) == set(panels)
    for config in panels.values():
        named |= {config.get("topic"), config.get("topicPath")} - {None}
        named |= set(config.get("topics", {}))
        named |= {config.get("imageMode", {}).get("imageTopic")} - {None}
        named |= {path["value"].split(".")[0] for path in config.get("paths", [])}
    graph = maze_server.lab.graphs[ROBOT]
    published = {name for name, topic in graph.topics.items() if topic.publishers}
    assert named <= published, named - published
    teleop = panels["Teleop!drive"]
    assert teleop["topic"] == "/cmd_vel" and teleop["publishRate"] >= 4  # a Twist lapses in 0.5 s


def stalled_foxglove_client(port: int, path: str, channel: int) -> socket.socket:
    """A Foxglove client that subscribes to ``channel`` and then never reads (a tiny
    receive buffer, and nothing read past the handshake)."""
    sock = socket.socket()
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    sock.connect(("127.0.0.1", port))
    sock.sendall(
        f"GET {path} HTTP/1.1\r\nHost: x\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
        "Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n"
        "Sec-WebSocket-Protocol: foxglove.sdk.v1\r\n\r\n".encode()
    )
    answer = b""
    while b"\r\n\r\n" not in answer:
        answer += sock.recv(1)
    assert b" 101 " in answer and b"foxglove.sdk.v1" in answer, answer
    frame = json.dumps({"op": "subscribe", "subscriptions": [{"id": 1, "channelId": channel}]})
    data = frame.encode()
    sock.sendall(bytes([0x81, 0x80 | 126]) + len(data).to_bytes(2, "big") + b"\0\0\0\0" + data)
    return sock


async def watch_odometry(url: str, count: int, stalled: Callable[[int], Any]) -> list[int]:
    """Subscribe to /odom as a Foxglove client, start the stalled clients once the
    camera's channel id is known, and return the stamps of the next ``count`` messages."""
    async with ws_connect(url, subprotocols=[Subprotocol("foxglove.sdk.v1")]) as ws:
        channels: dict[str, int] = {}
        while "/odom" not in channels:
            frame = await asyncio.wait_for(ws.recv(), 10)
            if isinstance(frame, str) and json.loads(frame)["op"] == "advertise":
                channels |= {c["topic"]: c["id"] for c in json.loads(frame)["channels"]}
        subscriptions = [{"id": 5, "channelId": channels["/odom"]}]
        await ws.send(json.dumps({"op": "subscribe", "subscriptions": subscriptions}))
        await asyncio.to_thread(stalled, channels["/camera/image/compressed"])
        stamps: list[int] = []
        while len(stamps) < count:
            frame = await asyncio.wait_for(ws.recv(), 10)
            if isinstance(frame, bytes) and frame[0] == 1:
                stamps.append(struct.unpack_from("<Q", frame, 5)[0])
        return stamps


def camera_watchers(server: ServerThread) -> list[Any]:
    """The connections of the Foxglove clients subscribed to the camera (on the lab's loop)."""
    return [
        conn
        for conn in server.lab.bridge.connections
        if isinstance(conn.session, FoxgloveSession)
        and any(
            feed.channel.topic == "/camera/image/compressed"
            for feed in conn.session.capability(Channels).feeds.values()
        )
    ]


def test_clients_that_never_read_the_camera_do_not_starve_one_that_reads(maze_server):
    """Five Foxglove clients subscribe to the camera and never read: each holds at most
    the two newest frames in the bridge, and a client that reads gets every tick's
    odometry beside them, in order, none missing."""
    url = robot_url(maze_server)
    port = int(maze_server.url.rsplit(":", 1)[1])
    sockets: list[socket.socket] = []

    def shrink() -> int:
        """The kernel would first take 4 MB for each stalled client (a minute of this
        camera); a small send buffer on the lab's side of their sockets is a slow link,
        and the bridge's own queue is reached in a second."""
        watchers = camera_watchers(maze_server)
        for conn in watchers:
            conn.ws.transport.get_extra_info("socket").setsockopt(
                socket.SOL_SOCKET, socket.SO_SNDBUF, 4096
            )
        return len(watchers)

    def stall(camera: int) -> None:
        sockets.extend(stalled_foxglove_client(port, f"/robots/{ROBOT}", camera) for _ in range(5))
        deadline = time.monotonic() + 10
        while maze_server.call(shrink) < 5:
            assert time.monotonic() < deadline, "the stalled clients did not subscribe"
            time.sleep(0.05)

    try:
        stamps = asyncio.run(watch_odometry(url, 60, stall))
        held = maze_server.call(
            lambda: [c.session.outbox.topic_bytes for c in camera_watchers(maze_server)]
        )
    finally:
        for sock in sockets:
            sock.close()
    steps = {b - a for a, b in itertools.pairwise(stamps)}
    assert len(steps) == 1 and min(steps) > 0, sorted(steps)  # every tick, in order
    frame = 320 * 240  # far more than a JPEG of the camera (about 5 kB)
    assert len(held) == 5 and all(0 < size <= 2 * frame for size in held), held


def test_the_share_of_an_address_counts_both_protocols(tmp_path):
    """One address's share of the bridge (here 2 connections) is one share: a rosbridge
    client and a Foxglove client fill it, and a third of either kind is refused."""
    bridge = BridgeConfig(port=0, max_connections_per_address=2)
    with running(lab_config(tmp_path / "data", bridge=bridge)) as server:
        url = robot_url(server)
        foxglove_offer = [Subprotocol("foxglove.sdk.v1")]

        async def crowd() -> list[int]:
            async with ws_connect(url), ws_connect(url, subprotocols=foxglove_offer) as fox:
                assert fox.subprotocol == "foxglove.sdk.v1"
                refused = []
                for offer in (None, foxglove_offer):
                    try:
                        async with ws_connect(url, subprotocols=offer, open_timeout=10):
                            refused.append(101)
                    except InvalidStatus as err:
                        refused.append(err.response.status_code)
                return refused

        assert asyncio.run(crowd()) == [503, 503]
