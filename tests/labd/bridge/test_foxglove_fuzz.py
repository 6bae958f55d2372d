"""Property-based tests: random frames thrown at a Foxglove session.

Whatever a Foxglove client sends (ops with random fields, binary frames with random
opcodes, ids and bytes, messages on its channels that are no messages, calls that are
no requests), the session answers with statuses and failures, never an internal error,
and keeps working for the next frame; when it leaves it leaves nothing in the graph.
"""

from __future__ import annotations

import json
import logging
import struct

import orjson
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from labd.bridge.foxglove import wire
from labd.bridge.foxglove.session import FoxgloveSession, ServerInfo
from labd.bridge.rosapi import Rosapi
from labd.config import BridgeConfig
from labd.graph.graph import Graph
from tests.fakes import ManualTimers, RecordingTransport

small_ints = st.integers(-2, 40)
anything = st.none() | st.booleans() | small_ints | st.text(max_size=6) | st.lists(small_ints)
channel = st.fixed_dictionaries(
    {
        "id": small_ints,
        "topic": st.sampled_from(["/cmd_vel", "/odom", "/protected/x", "chatter", "", "a//b"]),
        "encoding": st.sampled_from(["cdr", "json", "ros1", "protobuf", ""]),
        "schemaName": st.sampled_from(
            [
                "geometry_msgs/Twist",
                "geometry_msgs/msg/Twist",
                "std_msgs/msg/String",
                "x",
                "a/b/c/d",
            ]
        ),
    },
    optional={"schema": st.text(max_size=10), "schemaEncoding": st.text(max_size=8)},
)
ops = st.one_of(
    st.fixed_dictionaries(
        {
            "op": st.just("subscribe"),
            "subscriptions": st.lists(
                st.fixed_dictionaries({"id": small_ints, "channelId": small_ints}), max_size=4
            ),
        }
    ),
    st.fixed_dictionaries(
        {"op": st.just("unsubscribe"), "subscriptionIds": st.lists(small_ints, max_size=4)}
    ),
    st.fixed_dictionaries({"op": st.just("advertise"), "channels": st.lists(channel, max_size=3)}),
    st.fixed_dictionaries(
        {"op": st.just("unadvertise"), "channelIds": st.lists(small_ints, max_size=3)}
    ),
    st.fixed_dictionaries(
        {"op": st.just("getParameters"), "parameterNames": st.lists(st.text(max_size=12))},
        optional={"id": st.text(max_size=4)},
    ),
    st.fixed_dictionaries(
        {
            "op": st.just("setParameters"),
            "parameters": st.lists(
                st.fixed_dictionaries({"name": st.text(max_size=12)}, optional={"value": anything})
            ),
        }
    ),
    st.sampled_from(
        [
            {"op": "subscribeConnectionGraph"},
            {"op": "unsubscribeConnectionGraph"},
            {"op": "subscribeParameterUpdates", "parameterNames": []},
            {"op": "fetchAsset", "uri": "package://x", "requestId": 1},
            {"op": "auth", "key": "k"},
        ]
    ),
    st.dictionaries(st.sampled_from(["op", "id", "channels"]), anything, max_size=3),
)
binary = st.one_of(
    st.builds(
        wire.client_message,
        st.integers(0, 40),
        st.binary(max_size=80),
    ),
    st.builds(
        wire.service_call_request,
        st.integers(0, 40),
        st.integers(0, 2**32 - 1),
        st.sampled_from(["cdr", "json", "xml", ""]),
        st.binary(max_size=40) | st.just(b"\x00\x01\x00\x00\x00") | st.just(b"{}"),
    ),
    st.binary(max_size=32),
    st.builds(lambda n: b"\x02" + struct.pack("<III", 1, 1, n), st.integers(0, 2**32 - 1)),
)


class _ErrorCounter(logging.Handler):
    def __init__(self) -> None:
        super().__init__(logging.ERROR)
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append(record)


def _run(registry, frames: list[str | bytes]) -> None:
    timers = ManualTimers()
    graph = Graph(registry, name="fuzz", clock=lambda: int(timers.now * 1e9))
    Rosapi(graph, ("/protected",))
    robot = graph.create_node("/robot")
    odom = robot.advertise("/odom", "nav_msgs/msg/Odometry", own=True)
    robot.subscribe("/cmd_vel", "geometry_msgs/msg/Twist", lambda m: None)
    counter = _ErrorCounter()
    logger = logging.getLogger("labd")
    logger.addHandler(counter)
    try:
        sessions = [
            FoxgloveSession(
                graph,
                BridgeConfig(),
                timers,
                RecordingTransport(),
                client_id=i,
                info=ServerInfo("fuzz", "fuzz"),
            )
            for i in (1, 2)
        ]
        for i, frame in enumerate(frames):
            session = sessions[i % 2]
            session.receive(frame)
            odom.publish({})
            while session.next_frames() is not None:
                pass
            timers.advance(0.01)
        probe = sessions[0]
        probe.receive(json.dumps({"op": "getParameters", "parameterNames": [], "id": "probe"}))
        replies = []
        while (batch := probe.next_frames()) is not None:
            replies += [orjson.loads(f.data) for f in batch if f.text]
        assert any(r.get("id") == "probe" for r in replies), replies
        for session in sessions:
            session.close()
        timers.advance(60)
        assert [n for n in graph.nodes if n.startswith("/bridge/")] == []
        assert graph.on_change == []
    finally:
        logger.removeHandler(counter)
    assert counter.records == [], [r.getMessage() for r in counter.records]


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(ops.map(json.dumps) | binary, min_size=1, max_size=12))
def test_random_frames_never_break_a_foxglove_session(registry, frames):
    """Random op-shaped text and random binary frames produce no internal error and
    leave a working session."""
    _run(registry, frames)
