"""The lab's bridge against a Foxglove SDK server, through the same Foxglove client.

Foxglove's own client (npm ``@foxglove/ws-protocol``, unmodified, run by
``tests/js/foxglove_diff.mjs``) talks ``foxglove.sdk.v1`` to (a) a live robot of the lab
and (b) a ``foxglove-sdk`` server (Foxglove's reference implementation) that carries the
lab's ``/odom``: the same schema, and the very CDR bytes the lab's graph delivers, logged
at the message's time after a Time broadcast of it. What the client observes of both must
agree: server info's shape, the channel, MessageData (bytes, timestamps, decoded values),
Time frames, and what a Twist it publishes becomes on the server's side.

One difference is intended: a client offering only ``foxglove.websocket.v1`` (the spec's
name, still the only one older clients know) is refused by the SDK and accepted by the lab.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from labd.bridge.foxglove.session import ENCODINGS
from labd.bridge.foxglove.wire import SDK, WEBSOCKET
from labd.graph.graph import Node
from labd.graph.message import Message
from tests.helpers.labs import MAZE, ServerThread, lab_config, running

foxglove = pytest.importorskip("foxglove", reason="foxglove-sdk is not installed")
from foxglove import Context  # noqa: E402  (after the skip: these need foxglove)
from foxglove.websocket import (  # noqa: E402
    Capability,
    Client,
    ClientChannel,
    ServerListener,
    WebSocketServer,
)

JS = Path(__file__).resolve().parents[1] / "js"
NODE = shutil.which("node")
TIMEOUT = 40  # seconds for one script; its own waits are bounded far below this
WAIT = 10  # seconds for the servers to take what the client sent

ODOM = "nav_msgs/msg/Odometry"
TWIST = "geometry_msgs/msg/Twist"
TURN = {"linear": {"x": 0.0, "y": 0.0, "z": 0.0}, "angular": {"x": 0.0, "y": 0.0, "z": 0.125}}
SENT = 3  # Twists the client sends to each server

pytestmark = [
    pytest.mark.integration,
    pytest.mark.skipif(NODE is None, reason="Node.js (node, version 20 or later) is not installed"),
]


class Listener(ServerListener):
    """What the SDK server hands its application of a client's channels and messages."""

    def __init__(self) -> None:
        self.changed = threading.Condition()
        self.advertised: list[ClientChannel] = []
        self.data: list[tuple[int, bytes]] = []  # (client channel id, payload)

    def on_client_advertise(self, client: Client, channel: ClientChannel) -> None:
        with self.changed:
            self.advertised.append(channel)
            self.changed.notify_all()

    def on_message_data(self, client: Client, client_channel_id: int, data: bytes) -> None:
        with self.changed:
            self.data.append((client_channel_id, bytes(data)))
            self.changed.notify_all()

    def wait_for(self, count: int) -> list[tuple[int, bytes]]:
        with self.changed:
            assert self.changed.wait_for(lambda: len(self.data) >= count, WAIT), (
                f"the SDK server got {len(self.data)} of {count} messages within {WAIT} s"
            )
            return list(self.data)


@dataclass(frozen=True)
class Sides:
    """What the client observed of each server, and what each server's side received."""

    lab: dict[str, Any]  # the observe scenario
    sdk: dict[str, Any]
    lab_websocket: dict[str, Any]  # the handshake, offering only foxglove.websocket.v1
    sdk_websocket: dict[str, Any]
    lab_publish: dict[str, Any]  # the publish scenario
    sdk_publish: dict[str, Any]
    odom_schema: str
    twist_schema: str
    tapped: set[tuple[int, bytes]]  # /odom in the lab's graph: (stamp in ns, CDR)
    lab_twists: list[bytes]  # /cmd_vel's CDR in the lab's graph
    sdk_channels: list[ClientChannel]
    sdk_twists: list[tuple[int, bytes]]  # (client channel id, payload)


def start_client(url: str, scenario: str, *, offered: str, twist: str) -> subprocess.Popen[str]:
    """``scenario`` of ``foxglove_diff.mjs`` against ``url``, started."""
    if not (JS / "node_modules" / "@foxglove" / "ws-protocol").is_dir():
        pytest.fail(f"{JS / 'node_modules'} has no @foxglove/ws-protocol: run `make setup`")
    assert NODE is not None
    env = {**os.environ, "FOXGLOVE_SUBPROTOCOLS": offered, "FOXGLOVE_TWIST": twist}
    return subprocess.Popen(
        [NODE, str(JS / "foxglove_diff.mjs"), url, scenario],
        cwd=JS,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def observed(proc: subprocess.Popen[str], what: str) -> dict[str, Any]:
    """The observations of a script started by ``start_client``, or the test fails."""
    try:
        out, err = proc.communicate(timeout=TIMEOUT)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, err = proc.communicate()
        pytest.fail(f"{what} ran over {TIMEOUT} s; stderr:\n{err}")
    assert proc.returncode == 0, f"{what} exited with {proc.returncode}:\n{err}{out}"
    scenarios: dict[str, Any] = json.loads(out)["scenarios"]
    (result,) = scenarios.values()
    return result  # type: ignore[no-any-return]


@pytest.fixture(scope="module")
def sides(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Sides]:
    with running(lab_config(tmp_path_factory.mktemp("lab"))) as server:
        yield from _sides(server)


def _sides(server: ServerThread) -> Iterator[Sides]:
    """A Foxglove SDK server beside ``server``'s lab, for as long as the module runs."""
    context = Context()  # this test's channels reach this test's server only
    listener = Listener()
    sdk = foxglove.start_server(
        name="foxglove-sdk",
        host="127.0.0.1",
        port=0,
        capabilities=[Capability.ClientPublish, Capability.Time],
        supported_encodings=list(ENCODINGS),
        server_listener=listener,
        context=context,
    )
    started: list[subprocess.Popen[str]] = []
    try:
        yield from _observe(server, sdk, context, listener, started)
    finally:
        for proc in started:
            if proc.poll() is None:  # a script left behind by a failure
                proc.kill()
                proc.communicate()
        sdk.stop()


def _observe(
    server: ServerThread,
    sdk: WebSocketServer,
    context: Context,
    listener: Listener,
    started: list[subprocess.Popen[str]],
) -> Iterator[Sides]:
    """Tap the lab's graph into ``sdk``, run the client against both, yield what it saw."""
    assert server.lab is not None
    graph = server.lab.graphs[MAZE.name]
    odom_schema = server.call(lambda: graph.types.definition_text(ODOM))
    twist_schema = server.call(lambda: graph.types.definition_text(TWIST))
    channel = foxglove.Channel(
        "/odom",
        schema=foxglove.Schema(name=ODOM, encoding="ros2msg", data=odom_schema.encode()),
        message_encoding="cdr",
        context=context,
    )
    tapped: list[tuple[int, bytes]] = []
    lab_twists: list[bytes] = []

    def forward(message: Message) -> None:  # on the lab's loop, as the bridge's feeds
        cdr = message.cdr()
        tapped.append((message.stamp_ns, cdr))
        sdk.broadcast_time(message.stamp_ns)
        channel.log(cdr, log_time=message.stamp_ns)

    def tap() -> Node:
        node = graph.create_node("/foxglove_differential")
        node.subscribe("/odom", ODOM, forward, hidden=True)
        node.subscribe("/cmd_vel", TWIST, lambda m: lab_twists.append(m.cdr()), hidden=True)
        return node

    node = server.call(tap)
    try:
        twist = json.dumps({"schema": twist_schema, "value": TURN, "count": SENT})
        lab_url = f"{server.url}/robots/{MAZE.name}"
        sdk_url = f"ws://127.0.0.1:{sdk.port}/"
        # The lab's robot starts a new episode at its first command: publish comes after.
        phases = (
            {
                "lab": (lab_url, "observe", SDK),
                "sdk": (sdk_url, "observe", SDK),
                "lab_websocket": (lab_url, "handshake", WEBSOCKET),
                "sdk_websocket": (sdk_url, "handshake", WEBSOCKET),
            },
            {"lab_publish": (lab_url, "publish", SDK), "sdk_publish": (sdk_url, "publish", SDK)},
        )
        seen: dict[str, Any] = {}
        for phase in phases:  # the scripts of a phase run side by side
            procs = {
                name: start_client(url, scenario, offered=offered, twist=twist)
                for name, (url, scenario, offered) in phase.items()
            }
            started.extend(procs.values())
            seen |= {name: observed(proc, name) for name, proc in procs.items()}
        sdk_twists = listener.wait_for(SENT)
        server.wait_until(lambda: len(lab_twists) >= SENT, WAIT)
        yield Sides(
            **seen,
            odom_schema=odom_schema,
            twist_schema=twist_schema,
            tapped=server.call(lambda: set(tapped)),
            lab_twists=server.call(lambda: list(lab_twists)),
            sdk_channels=list(listener.advertised),
            sdk_twists=sdk_twists,
        )
    finally:
        server.call(node.destroy)
        channel.close()


# -- what both say alike --------------------------------------------------------------------


def test_the_client_reports_no_errors_and_sees_no_warnings_from_either_server(sides: Sides) -> None:
    """Foxglove's client parses everything either server sends, and neither complains."""
    for side in (sides.lab, sides.sdk, sides.lab_publish, sides.sdk_publish):
        assert side["errors"] == []
        assert side["statuses"] == []
    assert sides.lab["protocol"] == sides.sdk["protocol"] == SDK


def test_server_info_has_the_same_shape(sides: Sides) -> None:
    """Server info has the same fields and encodings; the lab offers the SDK server's
    capabilities and more (its name, session, metadata and extra capabilities aside)."""
    lab, sdk = sides.lab["info"], sides.sdk["info"]
    assert set(lab) == set(sdk)
    assert lab["op"] == sdk["op"] == "serverInfo"
    assert lab["supportedEncodings"] == sdk["supportedEncodings"]  # the SDK's set to the lab's
    assert set(sdk["capabilities"]) == {"clientPublish", "time"}
    assert set(sdk["capabilities"]) <= set(lab["capabilities"])
    assert set(lab["capabilities"]) - set(sdk["capabilities"]) <= {
        "services",
        "parameters",
        "connectionGraph",
    }
    for info in (lab, sdk):
        assert isinstance(info["name"], str)
        assert isinstance(info["sessionId"], str)
        assert isinstance(info["metadata"], dict)


def test_odom_is_advertised_alike(sides: Sides) -> None:
    """/odom is the same channel on both: CDR, the ROS 2 definition byte for byte."""
    lab, sdk = sides.lab["channel"], sides.sdk["channel"]
    assert set(lab) == set(sdk)
    for key in ("topic", "encoding", "schemaName", "schemaEncoding", "schema"):
        assert lab[key] == sdk[key], key
    assert lab["encoding"] == "cdr"
    assert lab["schemaName"] == ODOM
    assert lab["schemaEncoding"] == "ros2msg"
    assert lab["schema"].encode() == sides.odom_schema.encode()


def test_message_data_carries_the_graph_s_cdr_at_the_message_s_time(sides: Sides) -> None:
    """Each MessageData holds the CDR the lab's graph carried, timed with that message's
    time, on both servers; a message both delivered is the same bytes and decodes alike."""
    by_time = {}
    for name, side in (("lab", sides.lab), ("sdk", sides.sdk)):
        messages = side["messages"]
        assert len(messages) >= 8, name
        stamps = [int(m["timestamp"]) for m in messages]
        assert stamps == sorted(set(stamps)), f"{name}: times not increasing: {stamps}"
        for m, stamp in zip(messages, stamps, strict=True):
            assert (stamp, bytes.fromhex(m["hex"])) in sides.tapped, f"{name} at {stamp}"
            assert m["trailing"] is False
        by_time[name] = {int(m["timestamp"]): m for m in messages}
    common = by_time["lab"].keys() & by_time["sdk"].keys()
    assert common, "no /odom message reached the client from both servers"
    for stamp in common:
        lab, sdk = by_time["lab"][stamp], by_time["sdk"][stamp]
        assert lab["hex"] == sdk["hex"]
        assert lab["value"] == sdk["value"]


def test_each_message_s_time_is_sent_as_a_time_frame(sides: Sides) -> None:
    """Both servers send a Time frame of each message's time; the lab sends it before the
    message (the SDK's Time and MessageData travel apart and may cross)."""
    for name, side in (("lab", sides.lab), ("sdk", sides.sdk)):
        times = {stamp for kind, stamp in side["order"] if kind == "time"}
        assert {m["timestamp"] for m in side["messages"]} <= times, name
    told: set[str] = set()
    for kind, stamp in sides.lab["order"]:
        if kind == "time":
            told.add(stamp)
        else:
            assert stamp in told, f"the lab sent a message of {stamp} before its Time frame"


def test_a_published_twist_arrives_as_the_same_cdr(sides: Sides) -> None:
    """The Twist the client publishes on /cmd_vel in CDR reaches the SDK's application as the
    client's bytes, and the lab's graph as the same bytes."""
    sent = bytes.fromhex(sides.lab_publish["sent"])
    assert bytes.fromhex(sides.sdk_publish["sent"]) == sent
    (advertised,) = sides.sdk_channels
    assert advertised.topic == "/cmd_vel"
    assert advertised.encoding == "cdr"
    assert advertised.schema_name == TWIST
    assert advertised.schema_encoding == "ros2msg"
    assert advertised.schema == sides.twist_schema.encode()
    assert [data for _, data in sides.sdk_twists] == [sent] * SENT
    assert {channel_id for channel_id, _ in sides.sdk_twists} == {advertised.id}
    assert sides.lab_twists == [sent] * SENT


# -- the one intended difference ------------------------------------------------------------


def test_only_the_lab_accepts_a_client_offering_foxglove_websocket_v1(sides: Sides) -> None:
    """Offering only foxglove.websocket.v1, the SDK server refuses the handshake (HTTP 400)
    while the lab accepts it, answers with that subprotocol and sends server info."""
    assert sides.sdk_websocket == {"opened": False, "status": 400}
    lab = sides.lab_websocket
    assert lab["opened"] is True
    assert lab["protocol"] == WEBSOCKET
    assert lab["serverInfo"]["op"] == "serverInfo"
