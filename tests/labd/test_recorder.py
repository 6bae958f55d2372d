"""The trial recorder: the MCAP file, the bag folder, the manifest, digests and differences."""

from __future__ import annotations

import asyncio
import hashlib
import re
import shutil
import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.writer import Writer
from mcap_ros2.decoder import DecoderFactory
from mcap_ros2.writer import Writer as Ros2Writer
from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import Reader as BagReader
from ruamel.yaml import YAML

from labd.graph.graph import Graph, Side
from labd.graph.message import Message
from labd.graph.types import TypeRegistry
from labd.recorder import (
    Recorder,
    RecordSummary,
    bag,
    data_digest,
    first_difference,
    read_channels,
    read_manifest,
    read_messages,
    write_bag_metadata,
)
from labd.sim.registry import TaskSpec
from labd.sim.robot import TWIST, Robot
from repository.digests import canonical_json
from repository.well_known import MANIFEST_KEY, MANIFEST_RECORD, SIDE_KEY
from tests.helpers.manifests import of_robot
from tests.labd.sim.drive import random_value
from tests.labd.sim.pointmass import TASK as POINTMASS

TICK_NS = 100_000_000  # the control tick of both tasks used here
MANIFEST_VALUE = {"task": "pointmass", "seed": 5, "parameters": {"goal_x": 1.0}, "note": "é"}


def digest_topics(robot: Robot) -> set[str]:
    task = robot.sim.task
    names = {o.name for o in task.observations} | {c.name for c in task.commands}
    return names | {"/clock", "/lab/episode"}


@dataclass
class Run:
    """A recorded drive: its summary, and every message as it was delivered live."""

    summary: RecordSummary
    robot: Robot
    topics: set[str]
    time_ns: int = 0  # the simulation's time at the end
    delivered: list[tuple[str, Message]] = field(default_factory=list)
    images: list[Message] = field(default_factory=list)


def record(
    registry: TypeRegistry,
    folder: Path,
    task: str | TaskSpec = POINTMASS,
    *,
    seed: int = 5,
    ticks: int = 12,
    change_at: int | None = None,
    camera: bool = False,
    chunk_size: int | None = None,
    manifest: bool = False,
    params: dict[str, Any] | None = None,
) -> Run:
    """Drive ``task`` in lockstep with seeded random Twist commands, recording it all.

    At tick ``change_at`` the command's linear.x is changed, as a controller that
    behaves differently once would.
    """
    graph = Graph(registry, name="recorder-test")
    robot = Robot(graph, task, params or {}, seed)
    topics = digest_topics(robot)
    options: dict[str, Any] = {} if chunk_size is None else {"chunk_size": chunk_size}
    if manifest:  # a trial's manifest, as the lab writes one
        options["manifest"] = of_robot(robot, seed)
    recorder = Recorder(graph, folder, digest_topics=topics, **options)
    run = Run(RecordSummary(folder, {}, "", None, None, 0), robot, topics)
    graph.taps.append(
        lambda topic, message, side, sender: run.delivered.append((topic.name, message))
    )
    client = graph.create_node("/controller", side=Side.CLIENT)
    if camera:
        client.subscribe("/camera/image/compressed", None, run.images.append)
    commands = [
        (client.advertise(c.name, c.type), graph.codec(c.type))
        for c in robot.sim.task.commands
        if c.type == TWIST
    ]
    rng = np.random.default_rng(seed)
    try:
        robot.publish()  # tick 0, now that the recorder listens (as the trial runner does)
        for tick in range(ticks):
            for publisher, codec in commands:
                value = random_value(codec, registry, rng)
                if tick == change_at:
                    value["linear"]["x"] = value["linear"]["x"] / 2 + 0.25
                publisher.publish(value)
            step(client, over=not robot.sim.running)
    finally:
        run.summary = recorder.finish()
    run.time_ns = robot.sim.time_ns
    robot.close()
    return run


def step(client: Any, *, over: bool = False) -> None:
    """Call /lab/step: it succeeds, or, ``over`` (the episode has ended), says it cannot."""
    answers: list[Any] = []
    client.call_service("/lab/step", None, answers.append)
    assert answers[0].response.data["success"] is not over, answers[0].response.data


def mcap_messages(path: Path) -> list[tuple[Any, Any, Any, Any]]:
    """Every message of an MCAP file with its schema, channel and decoded value."""
    with path.open("rb") as stream:
        reader = make_reader(stream, decoder_factories=[DecoderFactory()])
        return list(reader.iter_decoded_messages(log_time_order=False))


def summary_of(path: Path) -> Any:
    with path.open("rb") as stream:
        return make_reader(stream).get_summary()


# -- the MCAP file ---------------------------------------------------------------------------


def test_every_message_is_in_the_file_in_delivery_order(registry, tmp_path):
    """Each delivered message is in the file, in order, as its topic, CDR bytes and stamp."""
    run = record(registry, tmp_path / "trial")
    got = [
        (c.topic, m.log_time, m.publish_time, m.data)
        for _, c, m, _ in mcap_messages(run.summary.path)
    ]
    want = [(t, m.stamp_ns, m.stamp_ns, m.cdr()) for t, m in run.delivered]
    assert got == want
    # What was delivered is the whole drive: each tick's observations and command.
    ticks = [m.data["tick"] for t, m in run.delivered if t == "/lab/episode"]
    assert ticks == list(range(13))
    assert {t for t, _ in run.delivered} == {"/pose", "/slow", "/clock", "/lab/episode", "/cmd_vel"}
    assert run.summary.counts == {
        t: sum(1 for n, _ in run.delivered if n == t) for t in {n for n, _ in run.delivered}
    }
    assert "/camera/image/compressed" not in run.summary.counts  # no one watched it


def test_the_ros2_decoder_reads_every_topic_with_its_type_and_values(registry, tmp_path):
    """mcap_ros2 decodes every channel with its ros2msg schema to the values published."""
    run = record(registry, tmp_path / "trial", "icreate-maze", ticks=6)
    with run.summary.path.open("rb") as stream:
        reader = make_reader(stream)
        header, summary = reader.get_header(), reader.get_summary()
    assert header.profile == "ros2"
    assert summary is not None
    types = {c.topic: summary.schemas[c.schema_id].name for c in summary.channels.values()}
    published = {o.name: o.type for o in run.robot.sim.task.observations if not o.on_demand}
    published |= {"/cmd_vel": TWIST, "/clock": "rosgraph_msgs/msg/Clock"}
    published |= {"/lab/episode": "lab_msgs/msg/Episode"}
    assert types == published  # all but the camera, which no one watched
    for schema in summary.schemas.values():
        assert schema.encoding == "ros2msg"
        assert schema.data.decode() == registry.definition_text(schema.name)
    assert {c.message_encoding for c in summary.channels.values()} == {"cdr"}
    decoded = mcap_messages(run.summary.path)
    assert len(decoded) == len(run.delivered)
    for (_, channel, _, value), (topic, message) in zip(decoded, run.delivered, strict=True):
        assert channel.topic == topic
        if topic == "/odom":
            pose = message.data["pose"]["pose"]["position"]
            assert (
                value.pose.pose.position.x == pose["x"] and value.pose.pose.position.y == pose["y"]
            )
        elif topic == "/cmd_vel":
            assert value.linear.x == message.data["linear"]["x"]
            assert value.angular.z == message.data["angular"]["z"]
        elif topic == "/lab/episode":
            assert (value.tick, value.status) == (message.data["tick"], message.data["status"])
        elif topic == "/joint_states":
            assert list(value.name) == message.data["name"]
            assert list(value.position) == list(message.data["position"])


def test_log_times_are_simulation_times(registry, tmp_path):
    """Log times are simulation time (/clock's value, tick by tick), in file order too."""
    run = record(registry, tmp_path / "trial", ticks=7)
    messages = mcap_messages(run.summary.path)
    clocks = [(m.log_time, v.clock) for _, c, m, v in messages if c.topic == "/clock"]
    times = [m.log_time for _, _, m, _ in messages]
    assert times == sorted(times)  # so log-time order, as viewers read, is recording order
    assert [t for t, _ in clocks] == [tick * TICK_NS for tick in range(8)]
    assert all(t == clock.sec * 10**9 + clock.nanosec for t, clock in clocks)
    assert (run.summary.start_time, run.summary.end_time) == (0, 7 * TICK_NS)
    assert run.summary.end_time == run.time_ns


def test_sequence_numbers_count_per_channel(registry, tmp_path):
    """Each channel numbers its messages 0, 1, 2, ... on its own."""
    run = record(registry, tmp_path / "trial", ticks=6)
    sequences: dict[str, list[int]] = {}
    for _, channel, message, _ in mcap_messages(run.summary.path):
        sequences.setdefault(channel.topic, []).append(message.sequence)
    assert sequences["/slow"] == [0, 1]  # ticks 0 and 5
    assert all(seq == list(range(len(seq))) for seq in sequences.values())


def test_chunks_are_zstd_compressed_and_indexed(registry, tmp_path):
    """The summary lists several zstd chunks, smaller than their content, and statistics."""
    run = record(registry, tmp_path / "trial", ticks=20, chunk_size=2048)
    summary = summary_of(run.summary.path)
    assert len(summary.chunk_indexes) > 2
    assert {c.compression for c in summary.chunk_indexes} == {"zstd"}
    assert sum(c.compressed_size for c in summary.chunk_indexes) < sum(
        c.uncompressed_size for c in summary.chunk_indexes
    )
    assert summary.statistics.message_count == run.summary.message_count
    assert summary.statistics.chunk_count == len(summary.chunk_indexes)


def test_camera_images_are_recorded_when_someone_watches(registry, tmp_path):
    """A subscriber's JPEG frames are recorded as sensor_msgs/msg/CompressedImage."""
    run = record(registry, tmp_path / "trial", "icreate-maze", ticks=3, camera=True)
    frames = [
        (m.log_time, v)
        for schema, c, m, v in mcap_messages(run.summary.path)
        if c.topic == "/camera/image/compressed"
        and schema.name == "sensor_msgs/msg/CompressedImage"
    ]
    assert len(frames) == len(run.images) == 1 + 1 + 3  # the newcomer's, tick 0, 3 ticks
    for (time, value), seen in zip(frames, run.images, strict=True):
        assert time == seen.stamp_ns and value.format == "jpeg"
        assert bytes(value.data) == seen.data["data"] and bytes(value.data[:2]) == b"\xff\xd8"


# -- the manifest, the attachments, the end of the file ---------------------------------------


def test_manifest_metadata_and_attachments(registry, tmp_path):
    """The manifest is a metadata record of canonical JSON; attachments keep name, type, data."""
    graph = Graph(registry, name="m")
    robot = Robot(graph, POINTMASS, {}, 1)
    recorder = Recorder(
        graph, tmp_path, digest_topics=digest_topics(robot), manifest=MANIFEST_VALUE
    )
    robot.publish()
    step(graph.create_node("/c"))
    files = {
        "manifest.json": ("application/json", canonical_json(MANIFEST_VALUE).encode()),
        "model.xml": ("application/xml", b"<mujoco/>"),
        "controller.stderr.log": ("text/plain", b"Traceback ...\n"),
    }
    summary = recorder.finish(attachments=files)
    with summary.path.open("rb") as stream:
        reader = make_reader(stream)
        metadata = {m.name: m.metadata for m in reader.iter_metadata()}
        attachments = list(reader.iter_attachments())
    text = metadata[MANIFEST_RECORD][MANIFEST_KEY]
    assert text == '{"note":"é","parameters":{"goal_x":1.0},"seed":5,"task":"pointmass"}'
    assert read_manifest(tmp_path) == MANIFEST_VALUE
    assert text == canonical_json(dict(reversed(MANIFEST_VALUE.items())))  # order-free
    assert {a.name: (a.media_type, a.data) for a in attachments} == files
    assert {a.log_time for a in attachments} == {summary.end_time} == {TICK_NS}


def test_manifest_can_come_at_finish_but_only_once(registry, tmp_path):
    """A manifest given to finish is recorded; a second one is refused, the file complete."""
    graph = Graph(registry, name="m")
    robot = Robot(graph, POINTMASS, {}, 1)
    Recorder(graph, tmp_path / "a", digest_topics=digest_topics(robot)).finish(
        manifest=MANIFEST_VALUE
    )
    assert read_manifest(tmp_path / "a") == MANIFEST_VALUE
    twice = Recorder(graph, tmp_path / "b", digest_topics=set(), manifest={"x": 1})
    with pytest.raises(ValueError, match="already has its manifest"):
        twice.finish(manifest=MANIFEST_VALUE)
    assert read_manifest(tmp_path / "b") == {"x": 1}
    assert summary_of(tmp_path / "b" / "trial.mcap") is not None
    assert graph.taps == []


def test_a_crash_inside_the_block_still_leaves_a_complete_record(registry, tmp_path):
    """An exception in the with block propagates, and the file has its summary and bag."""
    graph = Graph(registry, name="crash")
    robot = Robot(graph, POINTMASS, {}, 2)
    client = graph.create_node("/c")
    with (
        pytest.raises(RuntimeError, match="the controller crashed"),
        Recorder(graph, tmp_path, digest_topics=digest_topics(robot)) as recorder,
    ):
        robot.publish()
        for _ in range(3):
            step(client)
        raise RuntimeError("the controller crashed")
    summary = summary_of(tmp_path / "trial.mcap")
    # /pose, /clock and /lab/episode at ticks 0..3, and /slow at tick 0 (no one watched the camera)
    assert summary.statistics.message_count == recorder.finish().message_count == 3 * 4 + 1
    assert (summary.statistics.message_start_time, summary.statistics.message_end_time) == (
        0,
        3 * TICK_NS,
    )
    assert (tmp_path / "metadata.yaml").exists()
    assert graph.taps == []


def test_finish_is_idempotent_and_stops_recording(registry, tmp_path):
    """A second finish returns the same summary; later messages are not recorded."""
    graph = Graph(registry, name="idem")
    robot = Robot(graph, POINTMASS, {}, 2)
    recorder = Recorder(graph, tmp_path, digest_topics=digest_topics(robot))
    robot.publish()
    first = recorder.finish()
    robot.publish()
    assert recorder.finish() is first
    assert first.size == (tmp_path / "trial.mcap").stat().st_size
    assert summary_of(first.path).statistics.message_count == first.message_count == 4
    assert set(first.counts) == {"/pose", "/slow", "/clock", "/lab/episode"}


def test_an_existing_record_is_never_overwritten(registry, tmp_path):
    """A second recorder on the same folder refuses to start."""
    graph = Graph(registry, name="twice")
    Recorder(graph, tmp_path, digest_topics=()).finish()
    with pytest.raises(FileExistsError):
        Recorder(graph, tmp_path, digest_topics=())


def test_an_empty_record_is_still_a_bag(registry, tmp_path):
    """A recorder that heard nothing leaves a valid, empty MCAP file and bag."""
    summary = Recorder(Graph(registry, name="empty"), tmp_path, digest_topics=()).finish()
    assert (summary.message_count, summary.start_time, summary.end_time) == (0, None, None)
    with AnyReader([tmp_path]) as reader:
        assert list(reader.messages()) == []


def test_a_topic_made_anew_keeps_its_channel(registry, tmp_path):
    """A topic forgotten by the graph and created again is recorded on the same channel."""
    graph = Graph(registry, name="anew")
    with Recorder(graph, tmp_path, digest_topics={"/chatter"}) as recorder:
        for text in ("one", "two"):
            node = graph.create_node("/talker")
            node.advertise("/chatter", "std_msgs/msg/String").publish({"data": text})
            node.destroy()
    assert recorder.finish().counts == {"/chatter": 2}
    assert len(summary_of(tmp_path / "trial.mcap").channels) == 1


# -- sides ------------------------------------------------------------------------------------


def record_both_sides(registry: TypeRegistry, folder: Path) -> tuple[Robot, RecordSummary]:
    """A lockstep tick with a client's command and /rosout lines from the lab and a client."""
    graph = Graph(registry, name="sides")
    robot = Robot(graph, POINTMASS, {}, seed=5)
    recorder = Recorder(graph, folder, digest_topics=digest_topics(robot))
    client = graph.create_node("/bridge/client_1", side=Side.CLIENT)
    try:
        robot.publish()
        client.advertise("/cmd_vel", TWIST).publish({"linear": {"x": 0.1}})
        graph.rosout(20, "labd", "from the lab")
        client.advertise("/rosout", "rcl_interfaces/msg/Log").publish({"msg": "from a client"})
        step(client)
    finally:
        summary = recorder.finish()
        robot.close()
    return robot, summary


def test_each_channel_names_the_side_that_published_on_it(registry, tmp_path):
    """One channel per topic and side, labd.side in its metadata; /rosout has one of each."""
    robot, summary = record_both_sides(registry, tmp_path)
    channels = read_channels(tmp_path)
    lab = {c.topic for c in channels if c.side is Side.LAB}
    observed = {o.name for o in robot.sim.task.observations if not o.on_demand}
    assert lab == observed | {"/clock", "/lab/episode", "/rosout"}
    assert {c.topic for c in channels if c.side is Side.CLIENT} == {"/cmd_vel", "/rosout"}
    assert len(channels) == len(lab) + 2
    with (tmp_path / "trial.mcap").open("rb") as stream:
        metadata = [c.metadata for c in make_reader(stream).get_summary().channels.values()]
    assert all(m[SIDE_KEY] in ("lab", "client") and "offered_qos_profiles" in m for m in metadata)
    assert summary.counts["/rosout"] == 2


def test_read_messages_picks_observations_or_actions_by_side(registry, tmp_path):
    """A reader that knows no task gets the client's messages, or the lab's, in recording order."""
    record_both_sides(registry, tmp_path)
    client = [(m.topic, m.side) for m in read_messages(tmp_path, side=Side.CLIENT)]
    assert client == [("/cmd_vel", Side.CLIENT), ("/rosout", Side.CLIENT)]
    lab = list(read_messages(tmp_path, side=Side.LAB))
    assert {m.topic for m in lab} >= {"/pose", "/clock", "/lab/episode", "/rosout"}
    assert all(m.side is Side.LAB for m in lab)
    rosout = [m.side for m in read_messages(tmp_path, topics=["/rosout"])]
    assert rosout == [Side.LAB, Side.CLIENT]


def test_a_topic_of_both_sides_is_one_topic_of_the_bag(registry, tmp_path):
    """rosbag2 knows topics: /rosout is listed once with both sides' messages, and rosbags reads them."""
    _, summary = record_both_sides(registry, tmp_path)
    bag_topics = [
        t["topic_metadata"]["name"]
        for t in YAML(typ="safe").load((tmp_path / "metadata.yaml").read_text())[
            "rosbag2_bagfile_information"
        ]["topics_with_message_count"]
    ]
    assert sorted(bag_topics) == sorted(summary.counts)
    with AnyReader([tmp_path]) as reader:
        connections = [c for c in reader.connections if c.topic == "/rosout"]
        lines = [
            reader.deserialize(raw, c.msgtype).msg for c, _, raw in reader.messages(connections)
        ]
    assert lines == ["from the lab", "from a client"]


def test_a_record_without_sides_reads_as_unknown(tmp_path):
    """Channels of records made before sides were kept have side None; a side filter skips them."""
    path = tmp_path / "old.mcap"
    with path.open("wb") as stream:
        writer = Ros2Writer(stream)
        schema = writer.register_msgdef("std_msgs/msg/String", "string data")
        writer.write_message("/chatter", schema, {"data": "hi"}, 0)
        writer.finish()
    assert [(m.topic, m.side) for m in read_messages(path)] == [("/chatter", None)]
    assert list(read_messages(path, side=Side.LAB)) == []
    assert [c.side for c in read_channels(path)] == [None]


# -- the bag folder ---------------------------------------------------------------------------


def test_rosbags_reads_the_folder_as_a_rosbag2_bag(registry, tmp_path):
    """rosbags' rosbag2 Reader and AnyReader open the folder and deserialize every message."""
    run = record(registry, tmp_path / "trial", "icreate-maze", ticks=4)
    folder = run.summary.folder
    with BagReader(folder) as bag:
        assert bag.message_count == run.summary.message_count
        assert (bag.start_time, bag.end_time) == (0, 4 * TICK_NS + 1)  # end is exclusive
        assert bag.ros_distro == "jazzy"
        latched = {
            c.topic
            for c in bag.connections
            if c.ext.offered_qos_profiles[0].durability.name == "TRANSIENT_LOCAL"
        }
        assert {"/tf_static", "/goal", "/odom"} <= latched and "/clock" not in latched
    with AnyReader([folder]) as reader:
        assert {c.topic: c.msgcount for c in reader.connections} == run.summary.counts
        got = [(c.topic, t, reader.deserialize(raw, c.msgtype)) for c, t, raw in reader.messages()]
    assert [(topic, t) for topic, t, _ in got] == [(n, m.stamp_ns) for n, m in run.delivered]
    episodes = [msg for topic, _, msg in got if topic == "/lab/episode"]
    assert [e.tick for e in episodes] == list(range(5))
    assert episodes[0].task == "icreate-maze"


def test_a_lone_mcap_file_becomes_a_bag_again(registry, tmp_path):
    """write_bag_metadata rebuilds metadata.yaml from the file's own rosbag2 record."""
    run = record(registry, tmp_path / "trial", ticks=3)
    lone = tmp_path / "download"
    lone.mkdir()
    shutil.copy(run.summary.path, lone / "data.mcap")
    write_bag_metadata(lone / "data.mcap")
    with AnyReader([lone]) as reader:
        assert sum(1 for _ in reader.messages()) == run.summary.message_count
    original = (run.summary.folder / "metadata.yaml").read_text()
    assert (lone / "metadata.yaml").read_text() == original.replace("trial.mcap", "data.mcap")


def test_write_bag_metadata_refuses_a_foreign_file(tmp_path):
    """An MCAP file without labd's rosbag2 record cannot be turned into a bag."""
    path = tmp_path / "other.mcap"
    with path.open("wb") as stream:
        writer = Writer(stream)
        writer.start(profile="ros2")
        writer.finish()
    with pytest.raises(ValueError, match="no rosbag2 metadata record"):
        write_bag_metadata(path)


# -- digests and differences ------------------------------------------------------------------


def test_same_seeded_drive_gives_the_same_digest(registry, tmp_path):
    """Two recordings of one seeded drive share their data digest and have no difference."""
    a = record(registry, tmp_path / "a", seed=9)
    b = record(registry, tmp_path / "b", seed=9)
    assert a.summary.data_digest == b.summary.data_digest
    assert first_difference(a.summary.folder, b.summary.folder, a.topics) is None
    assert data_digest(a.summary.path, a.topics) == a.summary.data_digest


def test_data_digest_from_the_file_equals_the_live_one(registry, tmp_path):
    """Recomputing the digest from a file (folder or path) gives what the recorder had."""
    run = record(registry, tmp_path / "trial", "icreate-maze", ticks=5, camera=True)
    assert data_digest(run.summary.folder, run.topics) == run.summary.data_digest
    assert data_digest(run.summary.path, run.topics - {"/camera/image/compressed"}) != (
        run.summary.data_digest
    )


def test_digest_covers_only_the_digest_topics(registry, tmp_path):
    """Messages on other topics (a log line) change the file but not the data digest."""
    graph = Graph(registry, name="d", clock=lambda: 7)
    with Recorder(graph, tmp_path / "a", digest_topics={"/x"}) as a:
        graph.create_node("/n").advertise("/x", "std_msgs/msg/String").publish({"data": "hi"})
    graph = Graph(registry, name="d", clock=lambda: 7)
    with Recorder(graph, tmp_path / "b", digest_topics={"/x"}) as b:
        graph.rosout(20, "/n", "a log line")
        graph.create_node("/n").advertise("/x", "std_msgs/msg/String").publish({"data": "hi"})
    assert a.finish().data_digest == b.finish().data_digest
    assert b.finish().counts == {"/rosout": 1, "/x": 1}


def test_digest_follows_the_documented_framing(registry, tmp_path):
    """The digest is sha256 of the tag, then per message its length-prefixed topic, time, data."""
    times = iter([7, 2**40 + 3])
    graph = Graph(registry, name="f", clock=lambda: next(times))
    with Recorder(graph, tmp_path, digest_topics={"/a", "/b_2"}) as recorder:
        node = graph.create_node("/n")
        sent = [
            node.advertise("/a", "std_msgs/msg/String").publish({"data": "bc"}),
            node.advertise("/b_2", "std_msgs/msg/UInt32").publish({"data": 5}),
        ]
    want = hashlib.sha256(b"labd data digest 1\n")
    for topic, message in zip(("/a", "/b_2"), sent, strict=True):
        name, data = topic.encode(), message.cdr()
        want.update(struct.pack("<I", len(name)) + name)
        want.update(struct.pack("<QQ", message.stamp_ns, len(data)) + data)
    assert [m.stamp_ns for m in sent] == [7, 2**40 + 3]
    assert recorder.finish().data_digest == want.hexdigest()


def test_a_changed_command_is_found_at_its_tick(registry, tmp_path):
    """One changed command gives another digest; the difference names its topic, time, tick."""
    a = record(registry, tmp_path / "a", seed=4, ticks=10)
    b = record(registry, tmp_path / "b", seed=4, ticks=10, change_at=6)
    assert a.summary.data_digest != b.summary.data_digest
    difference = first_difference(a.summary.folder, b.summary.folder, a.topics)
    assert difference is not None
    assert (difference.topic, difference.log_time, difference.tick) == ("/cmd_vel", 6 * TICK_NS, 6)
    stream = [(n, m) for n, m in a.delivered if n in a.topics]
    assert stream[difference.index][1].cdr() == difference.a.data
    assert difference.b is not None and difference.b.data != difference.a.data
    said = re.fullmatch(
        rf"diverged at tick 6 on /cmd_vel \(message {difference.index}\): "
        r"linear\.x is (\S+) in a, (\S+) in b",
        str(difference),
    )
    assert said, str(difference)  # the field that differs, and both its values
    assert float(said[2]) == float(said[1]) / 2 + 0.25


def test_an_observation_difference_finds_its_tick_ahead(registry, tmp_path):
    """An observation logged before its tick's /lab/episode still gets that tick."""
    a = record(registry, tmp_path / "a", seed=4, ticks=8)
    b = record(registry, tmp_path / "b", seed=4, ticks=8, change_at=3)
    topics = a.topics - {"/cmd_vel"}  # as if commands were not compared: the pose shows it
    difference = first_difference(a.summary.path, b.summary.path, topics)
    assert difference is not None
    assert (difference.topic, difference.log_time, difference.tick) == ("/pose", 4 * TICK_NS, 4)


def test_a_shorter_record_differs_where_it_ends(registry, tmp_path):
    """A record that stops early differs at its end, and the difference says which ended."""
    a = record(registry, tmp_path / "a", seed=4, ticks=5)
    b = record(registry, tmp_path / "b", seed=4, ticks=3)
    difference = first_difference(a.summary.folder, b.summary.folder, a.topics)
    assert difference is not None and difference.b is None
    assert (difference.topic, difference.log_time, difference.tick) == ("/cmd_vel", 3 * TICK_NS, 3)
    assert difference.what == "record b ended before it"
    reverse = first_difference(b.summary.folder, a.summary.folder, a.topics)
    assert reverse is not None and reverse.a is None and reverse.index == difference.index


async def test_a_deferred_recorder_writes_after_the_callback_the_same_record(registry, tmp_path):
    """A trial's recorder (``defer``) keeps a tick's messages while the callback that made
    them runs (the tick's answer leaves first) and writes them on the loop's next turns:
    the same messages, in the same order, with the same digest as one that writes at once."""
    graph = Graph(registry, name="deferred")
    robot = Robot(graph, "icreate-maze", {}, 2)
    topics = digest_topics(robot)
    now = Recorder(graph, tmp_path / "now", digest_topics=topics)
    later = Recorder(graph, tmp_path / "later", digest_topics=topics, defer=True)
    client = graph.create_node("/controller", side=Side.CLIENT)
    command = client.advertise("/cmd_vel", TWIST)
    robot.publish()
    for tick in range(15):
        command.publish({"linear": {"x": 0.3}, "angular": {"z": 0.1 * (tick % 3)}})
        step(client)
        assert later._pending  # told, not written yet
        await asyncio.sleep(0)
        await asyncio.sleep(0)
        assert not later._pending
    robot.publish()  # told last, written by finish
    assert later.counts == now.counts  # (reading the counts writes what was kept)
    a, b = now.finish(), later.finish()
    robot.close()
    assert a.data_digest == b.data_digest
    assert [m[2].data for m in mcap_messages(a.path)] == [m[2].data for m in mcap_messages(b.path)]


def test_a_deferred_recorder_without_an_event_loop_writes_at_once(registry, tmp_path):
    graph = Graph(registry, name="no loop")
    robot = Robot(graph, "icreate-maze", {}, 5)
    later = Recorder(graph, tmp_path / "later", digest_topics=digest_topics(robot), defer=True)
    robot.publish()
    assert not later._pending and later._by_key  # written: its channels exist
    assert later.finish().counts["/lab/episode"] == 1
    robot.close()


@pytest.mark.parametrize(
    "value",
    [
        {"a": 1, "b": {"c": [1, 2], "d": []}, "e": {}, "f": None, "g": True, "h": ""},
        {"list": [{"x": 1, "y": {"z": "word"}}, {"x": 2}], "words": ["a/b", "c_d"]},
        {"tricky": ["true", "No", "1.5", "a: b", "-x", "#c", " pad", "ünï", "null"]},
        {"nested": [[1, 2], [3]], "float": 1.5, 3: "int key"},
        {"qos": bag.dump_qos_v9([bag.qos(True), bag.qos(False)])},
    ],
    ids=["plain", "lists-of-mappings", "strings-to-quote", "not-plain", "qos"],
)
def test_the_bags_yaml_is_the_librarys_text(value):
    """``bag.to_yaml`` writes simple values itself (a bag's information at the end of
    every trial) and leaves the rest to the YAML library: the same text either way."""
    assert bag.to_yaml(value) == bag._library_yaml(value)


def test_a_records_bag_information_is_written_as_the_library_writes_it(registry, tmp_path):
    run = record(registry, tmp_path / "r", "icreate-maze", ticks=3)
    text = (run.summary.folder / bag.BAG_METADATA).read_text()
    info = YAML(typ="safe").load(text)["rosbag2_bagfile_information"]
    assert bag.to_yaml(info) == bag._library_yaml(info)
    assert len(info["topics_with_message_count"]) > 5
