"""Property-based tests: random frames thrown at the protocol core.

Whatever a client sends, the session must answer with statuses, never with an
internal error, and must keep working for the next frame.
"""

from __future__ import annotations

import json
import logging

import orjson
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from labd.bridge.frames import OP_NAMES
from labd.bridge.ops import CAPABILITIES
from labd.bridge.rosapi import Rosapi
from labd.bridge.session import Session
from labd.config import BridgeConfig
from labd.graph.codec import codec_for, dumps
from labd.graph.graph import Graph
from tests.fakes import ManualTimers, RecordingTransport, drain

json_scalars = (
    st.none()
    | st.booleans()
    | st.integers(-(2**70), 2**70)
    | st.floats(allow_nan=False, allow_infinity=False)
    | st.text(max_size=20)
)
json_values = st.recursive(
    json_scalars,
    lambda inner: (
        st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner, max_size=4)
    ),
    max_leaves=12,
)
names = st.sampled_from(
    [
        "/chatter",
        "chatter",
        "/rosapi/topics",
        "/protected/x",
        "",
        "a//b",
        "/cmd_vel",
        "/fib",
        "/add",
        5,
    ]
)
types = st.sampled_from(
    [
        "std_msgs/String",
        "geometry_msgs/msg/Twist",
        "nope/Nope",
        "example_interfaces/action/Fibonacci",
        "example_interfaces/AddTwoInts",
        "std_srvs/srv/Trigger",
        3,
    ]
)
op_frames = st.fixed_dictionaries(
    {"op": st.sampled_from(OP_NAMES)},
    optional={
        "id": st.text(max_size=5) | st.integers(0, 5),
        "topic": names,
        "service": names,
        "action": names,
        "type": types,
        "action_type": types,
        "msg": json_values,
        "args": json_values,
        "values": json_values,
        "throttle_rate": st.integers(-5, 200),
        "queue_length": st.integers(-1, 3),
        "fragment_size": st.integers(-1, 50),
        "compression": st.sampled_from(["none", "png", "cbor", "cbor-raw", "zip"]),
        "level": st.sampled_from(["info", "warning", "error", "none", "loud"]),
        "result": st.booleans(),
        "status": st.integers(-1, 8),
        "feedback": st.booleans(),
        "timeout": st.floats(-1, 10),
        "data": st.text(max_size=10),
        "num": st.integers(-1, 3),
        "total": st.integers(-1, 3),
        "latch": st.booleans(),
        "key": st.text(max_size=5),
    },
)


class _ErrorCounter(logging.Handler):
    def __init__(self) -> None:
        super().__init__(logging.ERROR)
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append(record)


def _run(registry, frames: list[bytes]) -> None:
    timers = ManualTimers()
    graph = Graph(registry, name="fuzz", clock=lambda: int(timers.now * 1e9))
    Rosapi(graph, ("/protected",))
    counter = _ErrorCounter()
    logger = logging.getLogger("labd")
    logger.addHandler(counter)
    try:
        sessions = [
            Session(
                graph,
                BridgeConfig(),
                timers,
                RecordingTransport(),
                client_id=i,
                capabilities=CAPABILITIES,
            )
            for i in (1, 2)
        ]
        for i, frame in enumerate(frames):
            sessions[i % 2].receive(frame)
            drain(sessions[i % 2])
            timers.advance(0.01)
        probe = sessions[0]
        probe.receive(b'{"op":"call_service","id":"probe","service":"/rosapi/get_ros_version"}')
        replies = [f for f in drain(probe) if f.get("id") == "probe"]
        assert replies and replies[-1]["result"] is True
        for session in sessions:
            session.close()
        timers.advance(60)
        assert [n for n in graph.nodes if n.startswith("/bridge/")] == []
    finally:
        logger.removeHandler(counter)
    assert counter.records == [], [r.getMessage() for r in counter.records]


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(op_frames.map(json.dumps), min_size=1, max_size=12))
def test_random_ops_never_break_the_session(registry, frames):
    """Random op-shaped frames produce no internal error and leave a working session."""
    _run(registry, frames)


@settings(max_examples=200, deadline=None)
@given(st.lists(st.binary(max_size=64) | json_values.map(json.dumps), min_size=1, max_size=8))
def test_random_bytes_never_break_the_session(registry, frames):
    """Random bytes and random JSON produce no internal error and leave a working session."""
    _run(registry, frames)


vector = st.fixed_dictionaries(
    {}, optional={k: st.floats(allow_nan=False, allow_infinity=False, width=64) for k in "xyz"}
)


@settings(max_examples=200, deadline=None)
@given(st.fixed_dictionaries({}, optional={"linear": vector, "angular": vector}))
def test_normal_form_is_a_fixed_point(registry, value):
    """Normalizing the JSON rendering of a normalized message gives it back unchanged."""
    codec = codec_for(registry, "geometry_msgs/msg/Twist")
    once = codec.normalize(value, lambda: (0, 0))
    twice = codec.normalize(orjson.loads(dumps(once)), lambda: (0, 0))
    assert twice == once


@settings(max_examples=150, deadline=None)
@given(
    st.fixed_dictionaries(
        {},
        optional={
            "name": st.lists(st.text(max_size=6), max_size=4),
            "position": st.lists(st.floats(allow_nan=False, width=64), max_size=4),
            "effort": st.lists(st.integers(-(2**40), 2**40), max_size=3),
            "header": st.fixed_dictionaries(
                {
                    "frame_id": st.text(max_size=5),
                    "stamp": st.fixed_dictionaries(
                        {
                            "sec": st.integers(-(2**31), 2**31 - 1),
                            "nanosec": st.integers(0, 2**32 - 1),
                        }
                    ),
                }
            ),
        },
    )
)
def test_cdr_round_trip(registry, value):
    """Any valid JointState survives CDR serialization and back."""
    codec = codec_for(registry, "sensor_msgs/msg/JointState")
    data = codec.normalize(value, lambda: (0, 0))
    raw = registry.typestore.serialize_cdr(codec.to_rosbags(data), codec.type.name)
    back = codec.from_rosbags(registry.typestore.deserialize_cdr(raw, codec.type.name))
    assert orjson.loads(dumps(back)) == orjson.loads(dumps(data))
