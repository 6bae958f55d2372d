"""Exports of a real record (icreate-maze, lockstep, the Recorder) to Parquet and LeRobot v3.0."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from mcap.writer import Writer as McapWriter
from mcap_ros2.writer import Writer as Ros2Writer

from labd.graph.graph import Graph, Side
from labd.graph.types import TypeRegistry
from labd.recorder import Recorder
from labd.sim import registry
from labd.sim.robot import Robot
from scheduler.manifest import versions
from repository.errors import ExportError
from repository.export import export

TASK = "icreate-maze"
TICKS = 24
CAMERA = "/camera/image/compressed"
OBSERVATIONS = ["/odom", "/joint_states", "/bumper", "/goal", CAMERA]
ACTIONS = ["/cmd_vel"]
PROVENANCE = {
    "trial": 7,
    "repository": "https://example.org/lab/maze.git",
    "commit": "0123456789abcdef0123456789abcdef01234567",
    "manifest": {"task": TASK, "seed": 3, "parameters": {"time_limit": 60.0}},
    "manifest_digest": "ab" * 32,
    "data_digest": "cd" * 32,
}


def command(tick: int) -> dict[str, Any] | None:
    """The /cmd_vel sent before step ``tick``: none every fourth tick (so the last one holds)."""
    if tick % 4 == 2:
        return None
    return {"linear": {"x": 0.02 * tick}, "angular": {"z": 0.25 * ((tick % 5) - 2)}}


@dataclass
class Drive:
    """A recorded lockstep drive and what was delivered live."""

    mcap: Path
    sent: list[dict[str, Any]] = field(default_factory=list)  # in effect during step k
    observed: list[dict[str, Any]] = field(default_factory=list)  # tick k: topic -> data
    episodes: list[dict[str, Any]] = field(default_factory=list)  # /lab/episode per tick


def drive(
    folder: Path,
    *,
    ticks: int = TICKS,
    first_command: int = 0,
    camera: bool = True,
    reset_after: int | None = None,
) -> Drive:
    """Drive icreate-maze in lockstep, publishing ``command(k)`` before each step."""
    graph = Graph(TypeRegistry.default(), name="export-test")
    robot = Robot(graph, TASK, {}, 3)
    task = robot.sim.task
    topics = {o.name for o in task.observations} | {c.name for c in task.commands}
    manifest = {
        "task": {"name": TASK, "version": registry.get(TASK).version},
        "parameters": registry.validate(TASK, {}),
        "seed": 3,
        "versions": versions(),
        "model_sha256": robot.sim.model_digest(),
        "repository": PROVENANCE["repository"],
        "commit": PROVENANCE["commit"],
    }
    recorder = Recorder(graph, folder, digest_topics=topics, manifest=manifest)
    run = Drive(folder / "trial.mcap")
    latest: dict[str, Any] = {}

    def tap(topic: Any, message: Any, side: Side) -> None:
        latest[topic.name] = message.data
        if topic.name == "/lab/episode":
            run.observed.append(dict(latest))
            run.episodes.append(message.data)

    graph.taps.append(tap)
    client = graph.create_node("/controller", side=Side.CLIENT)
    if camera:
        client.subscribe(CAMERA, None, lambda message: None)
    cmd_vel = client.advertise("/cmd_vel", "geometry_msgs/msg/Twist")
    held: dict[str, Any] = {}
    try:
        robot.publish()
        for tick in range(ticks):
            if tick == reset_after:
                robot.reset(3)
                held = {}
            value = command(tick) if tick >= first_command else None
            if value is not None:
                cmd_vel.publish(value)
                held = value
            run.sent.append(held)
            answers: list[Any] = []
            client.call_service("/lab/step", None, answers.append)
            assert answers[0].response.data["success"]
    finally:
        recorder.finish()
        robot.close()
    return run


@pytest.fixture(scope="module")
def trial(tmp_path_factory: pytest.TempPathFactory) -> Drive:
    return drive(tmp_path_factory.mktemp("trial"))


def run_export(trial: Drive, out: Path, fmt: str, **kwargs: Any) -> Any:
    options: dict[str, Any] = {
        "observations": OBSERVATIONS,
        "actions": ACTIONS,
        "provenance": PROVENANCE,
    }
    options.update(kwargs)
    return export(trial.mcap, out, fmt, **options)


# -- parquet ----------------------------------------------------------------------------------


def test_parquet_pairs_each_observation_with_the_command_that_followed(trial, tmp_path):
    """One row per step: tick k's observations, the command in effect for step k, its reward."""
    summary = run_export(trial, tmp_path / "out", "parquet")
    assert summary.files == (tmp_path / "out" / "data.parquet",)
    assert (summary.frames, summary.episodes, summary.dropped) == (TICKS, 1, 1)  # last: no step
    rows = pq.read_table(summary.files[0]).to_pylist()
    assert len(rows) == TICKS
    assert [r["tick"] for r in rows] == [r["frame_index"] for r in rows] == list(range(TICKS))
    assert [r["timestamp"] for r in rows] == pytest.approx([k / 10 for k in range(TICKS)])
    for k, row in enumerate(rows):
        sent = trial.sent[k]
        assert row["action./cmd_vel.linear.x"] == sent["linear"]["x"]
        assert row["action./cmd_vel.angular.z"] == sent["angular"]["z"]
        assert row["action./cmd_vel.linear.y"] == 0.0
        seen = trial.observed[k]
        position = seen["/odom"]["pose"]["pose"]["position"]
        assert row["observation./odom.pose.pose.position.x"] == position["x"]
        assert row["observation./odom.pose.pose.position.y"] == position["y"]
        assert row["observation./joint_states.position[1]"] == seen["/joint_states"]["position"][1]
        assert row["observation./bumper.left"] is seen["/bumper"]["left"]
        assert row["observation./goal.point.x"] == seen["/goal"]["point"]["x"]  # sent once, held
        assert row[f"observation.{CAMERA}.data"] == bytes(seen[CAMERA]["data"])
        assert row[f"observation.{CAMERA}.format"] == "jpeg"
        assert row["next.reward"] == trial.episodes[k + 1]["reward"]
        assert row["next.done"] is False
    assert rows[0][f"observation.{CAMERA}.data"][:2] == b"\xff\xd8"
    assert len({r["observation./odom.pose.pose.position.x"] for r in rows}) > TICKS // 2  # moved


def test_a_command_holds_when_the_controller_sent_none(trial, tmp_path):
    """Before steps without a new /cmd_vel, the action is the previous command."""
    rows = pq.read_table(run_export(trial, tmp_path / "out", "parquet").files[0]).to_pylist()
    for k in range(2, TICKS, 4):
        assert rows[k]["action./cmd_vel.linear.x"] == command(k - 1)["linear"]["x"]
        assert rows[k]["action./cmd_vel.angular.z"] == command(k - 1)["angular"]["z"]


def test_parquet_carries_provenance_and_typed_columns(trial, tmp_path):
    """Provenance is JSON in the schema metadata; columns follow the field types."""
    summary = run_export(trial, tmp_path / "out", "parquet")
    schema = pq.read_schema(summary.files[0])
    assert json.loads(schema.metadata[PROVENANCE_KEY.encode()]) == PROVENANCE
    types = {name: str(schema.field(name).type) for name in schema.names}
    assert types[f"observation.{CAMERA}.data"] == "binary"
    assert types["observation./odom.header.frame_id"] == "string"
    assert types["observation./bumper.right"] == "bool"
    assert types["observation./odom.header.stamp.sec"] == "int64"
    assert types["action./cmd_vel.linear.x"] == "double"
    assert set(summary.observation_names) | set(summary.action_names) == {
        n for n in schema.names if n.startswith(("observation.", "action."))
    }
    assert summary.action_names == tuple(
        f"action./cmd_vel.{part}.{axis}" for part in ("linear", "angular") for axis in "xyz"
    )


# -- lerobot ----------------------------------------------------------------------------------


def test_lerobot_v3_layout_and_values(trial, tmp_path):
    """The v3.0 layout: info, stats, tasks, episodes, data with float32 vectors and names."""
    out = tmp_path / "dataset"
    summary = run_export(trial, out, "lerobot")
    assert sorted(str(p.relative_to(out)) for p in out.rglob("*") if p.is_file()) == [
        "data/chunk-000/file-000.parquet",
        "meta/episodes/chunk-000/file-000.parquet",
        "meta/info.json",
        "meta/stats.json",
        "meta/tasks.parquet",
    ]
    info = json.loads((out / "meta" / "info.json").read_text())
    assert info["codebase_version"] == "v3.0"
    assert (info["fps"], info["total_episodes"], info["total_frames"]) == (10, 1, TICKS)
    assert info["data_path"] == "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
    assert info["labd"]["provenance"] == PROVENANCE
    features = info["features"]
    state_names = features["observation.state"]["names"]
    action_names = features["action"]["names"]
    assert features["observation.state"]["shape"] == [len(state_names)]
    assert features["action"]["shape"] == [6] and features["action"]["dtype"] == "float32"
    assert (
        action_names
        == list(summary.action_names)
        == [f"/cmd_vel.{part}.{axis}" for part in ("linear", "angular") for axis in "xyz"]
    )
    assert tuple(state_names) == summary.observation_names
    assert not any("stamp" in name or CAMERA in name for name in state_names)
    assert "/bumper.left" in state_names and "/goal.point.y" in state_names

    table = pq.read_table(out / info["data_path"].format(chunk_index=0, file_index=0))
    assert set(table.column_names) == set(features)
    vector = table.schema.field("observation.state").type
    assert pa.types.is_fixed_size_list(vector) and vector.value_type == pa.float32()
    assert vector.list_size == len(state_names)
    state = np.array(table.column("observation.state").to_pylist(), np.float32)
    action = np.array(table.column("action").to_pylist(), np.float32)
    assert state.shape == (TICKS, len(state_names)) and action.shape == (TICKS, 6)
    x = state_names.index("/odom.pose.pose.position.x")
    wheel = state_names.index("/joint_states.velocity[0]")
    for k in range(TICKS):
        seen, sent = trial.observed[k], trial.sent[k]
        assert state[k, x] == np.float32(seen["/odom"]["pose"]["pose"]["position"]["x"])
        assert state[k, wheel] == np.float32(seen["/joint_states"]["velocity"][0])
        assert action[k, 0] == np.float32(sent["linear"]["x"])
        assert action[k, 5] == np.float32(sent["angular"]["z"])
    assert table.column("frame_index").to_pylist() == list(range(TICKS))
    assert table.column("index").to_pylist() == list(range(TICKS))
    assert set(table.column("episode_index").to_pylist()) == {0}
    assert set(table.column("task_index").to_pylist()) == {0}
    assert table.column("timestamp").to_pylist() == pytest.approx([k / 10 for k in range(TICKS)])

    stats = json.loads((out / "meta" / "stats.json").read_text())
    assert set(stats) == set(features)
    assert stats["action"]["count"] == [TICKS]
    assert stats["action"]["max"][0] == pytest.approx(float(action[:, 0].max()))
    assert len(stats["observation.state"]["q50"]) == len(state_names)
    tasks = pq.read_table(out / "meta" / "tasks.parquet")
    assert tasks.to_pylist() == [{"task_index": 0, "task": TASK}]
    assert json.loads(tasks.schema.metadata[b"pandas"])["index_columns"] == ["task"]
    episodes = pq.read_table(out / "meta" / "episodes" / "chunk-000" / "file-000.parquet")
    episode = episodes.to_pylist()[0]
    assert (episode["episode_index"], episode["length"], episode["tasks"]) == (0, TICKS, [TASK])
    assert (episode["dataset_from_index"], episode["dataset_to_index"]) == (0, TICKS)
    assert episode["stats/action/count"] == [TICKS]


def test_a_reset_starts_a_new_episode(tmp_path):
    """A record with two episodes exports two, each numbered from frame 0."""
    run = drive(tmp_path / "trial", ticks=9, camera=False, reset_after=5)
    summary = export(
        run.mcap,
        tmp_path / "out",
        "lerobot",
        observations=["/odom"],
        actions=ACTIONS,
        provenance={},
    )
    assert (summary.frames, summary.episodes, summary.dropped) == (9, 2, 2)  # ends: no step
    table = pq.read_table(tmp_path / "out" / "data" / "chunk-000" / "file-000.parquet")
    assert table.column("episode_index").to_pylist() == [0] * 5 + [1] * 4
    assert table.column("frame_index").to_pylist() == [0, 1, 2, 3, 4, 0, 1, 2, 3]
    actions = np.array(table.column("action").to_pylist())
    assert actions[5, 0] == np.float32(command(5)["linear"]["x"])
    episodes = pq.read_table(
        tmp_path / "out" / "meta" / "episodes" / "chunk-000" / "file-000.parquet"
    )
    assert episodes.column("length").to_pylist() == [5, 4]
    assert episodes.column("dataset_from_index").to_pylist() == [0, 5]


# -- which frames, which topics ---------------------------------------------------------------


def test_frames_begin_once_every_action_topic_has_a_message(tmp_path):
    """Ticks before the controller's first command make no frame; the summary counts them."""
    run = drive(tmp_path / "trial", ticks=8, first_command=3, camera=False)
    summary = export(
        run.mcap,
        tmp_path / "out",
        "parquet",
        observations=OBSERVATIONS,
        actions=ACTIONS,
        provenance={},
    )
    rows = pq.read_table(summary.files[0]).to_pylist()
    assert [r["tick"] for r in rows] == [3, 4, 5, 6, 7]
    assert summary.dropped == 4  # ticks 0, 1, 2 and the last, 8
    assert summary.missing_topics == (CAMERA,)  # no one watched it: left out, listed
    assert not any(CAMERA in name for name in summary.observation_names)


def test_variable_length_fields_become_json_and_strings_stay_strings(tmp_path):
    """Sequences whose length changes are JSON text; byte arrays binary; strings strings."""
    path = tmp_path / "synthetic.mcap"
    with path.open("wb") as stream:
        writer = Ros2Writer(stream)
        episode = writer.register_msgdef(
            "lab_msgs/msg/Episode",
            "string task\nuint32 tick\nstring status\nfloat64 reward\nbool success",
        )
        scan = writer.register_msgdef(
            "test_msgs/msg/Scan", "float64[] ranges\nstring label\nuint8[] blob\nint32[3] ids"
        )
        twist = writer.register_msgdef("test_msgs/msg/Speed", "float32 speed")
        for tick in range(4):
            time = tick * 50_000_000
            writer.write_message(
                "/scan",
                scan,
                {
                    "ranges": [0.5] * tick,
                    "label": f"t{tick}",
                    "blob": bytes([tick]),
                    "ids": [tick, 2, 3],
                },
                time,
            )
            writer.write_message(
                "/lab/episode",
                episode,
                {"task": "t", "tick": tick, "status": "running", "reward": 1.0, "success": False},
                time,
            )
            writer.write_message("/speed", twist, {"speed": tick / 4}, time)
        writer.finish()
    summary = export(
        path, tmp_path / "out", "parquet", observations=["/scan"], actions=["/speed"], provenance={}
    )
    rows = pq.read_table(summary.files[0]).to_pylist()
    assert [json.loads(r["observation./scan.ranges"]) for r in rows] == [
        [0.5] * k for k in range(3)
    ]
    assert [r["observation./scan.label"] for r in rows] == ["t0", "t1", "t2"]
    assert [r["observation./scan.blob"] for r in rows] == [b"\x00", b"\x01", b"\x02"]
    assert [r["observation./scan.ids[0]"] for r in rows] == [0, 1, 2]
    assert [r["action./speed.speed"] for r in rows] == [0.0, 0.25, 0.5]
    lerobot = export(
        path, tmp_path / "lr", "lerobot", observations=["/scan"], actions=["/speed"], provenance={}
    )
    assert lerobot.observation_names == ("/scan.ids[0]", "/scan.ids[1]", "/scan.ids[2]")
    assert json.loads((tmp_path / "lr" / "meta" / "info.json").read_text())["fps"] == 20


# -- bad input --------------------------------------------------------------------------------


def test_an_unknown_format_names_the_formats(trial, tmp_path):
    """An unknown format is refused before anything is written."""
    with pytest.raises(ExportError, match="parquet, lerobot"):
        run_export(trial, tmp_path / "out", "hdf5")
    assert list(tmp_path.iterdir()) == []


def test_a_missing_or_unreadable_mcap_is_refused(trial, tmp_path):
    """No file, a file that is not MCAP and a truncated record are ExportErrors."""
    with pytest.raises(ExportError, match="no MCAP file"):
        export(
            tmp_path / "nope.mcap",
            tmp_path / "a",
            "parquet",
            observations=OBSERVATIONS,
            actions=ACTIONS,
            provenance={},
        )
    garbage = tmp_path / "garbage.mcap"
    garbage.write_bytes(b"not an mcap file at all" * 10)
    truncated = tmp_path / "truncated.mcap"
    data = trial.mcap.read_bytes()
    truncated.write_bytes(data[: len(data) // 2])
    for path in (garbage, truncated):
        with pytest.raises(ExportError, match="not a complete, readable MCAP file"):
            export(
                path,
                tmp_path / "b",
                "parquet",
                observations=OBSERVATIONS,
                actions=ACTIONS,
                provenance={},
            )
    assert sorted(p.name for p in tmp_path.iterdir()) == ["garbage.mcap", "truncated.mcap"]


def test_a_record_without_the_named_topics_is_refused(trial, tmp_path):
    """None of the observation (or action) topics in the record is an ExportError naming them."""
    with pytest.raises(
        ExportError, match=r"none of the observation topics /lidar; it records .*/odom"
    ):
        run_export(trial, tmp_path / "a", "parquet", observations=["/lidar"])
    with pytest.raises(ExportError, match="none of the action topics /arm/command"):
        run_export(trial, tmp_path / "b", "lerobot", actions=["/arm/command"])
    assert list(tmp_path.iterdir()) == []


def test_a_failed_export_leaves_no_folder(trial, tmp_path):
    """An export that fails while writing removes what it wrote."""
    with pytest.raises(ExportError, match="no fixed-length numeric field"):
        run_export(trial, tmp_path / "out", "lerobot", observations=[CAMERA])
    assert list(tmp_path.iterdir()) == []


def test_an_existing_output_and_bad_provenance_are_refused(trial, tmp_path):
    """A non-empty output folder is never overwritten; provenance must be JSON."""
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    with pytest.raises(ExportError, match="already exists"):
        run_export(trial, out, "parquet")
    assert [p.name for p in out.iterdir()] == ["keep.txt"]
    with pytest.raises(ExportError, match="provenance must be JSON"):
        run_export(trial, tmp_path / "new", "parquet", provenance={"when": object()})
    empty = tmp_path / "empty"
    empty.mkdir()
    assert run_export(trial, empty, "parquet").frames == TICKS  # an empty folder is fine


def test_a_record_without_episodes_is_refused(tmp_path):
    """Without /lab/episode the ticks are unknown: an ExportError says so."""
    path = tmp_path / "plain.mcap"
    with path.open("wb") as stream:
        writer = Ros2Writer(stream)
        speed = writer.register_msgdef("test_msgs/msg/Speed", "float32 speed")
        writer.write_message("/speed", speed, {"speed": 1.0}, 0)
        writer.write_message("/odom", speed, {"speed": 1.0}, 0)
        writer.finish()
    with pytest.raises(ExportError, match="no /lab/episode"):
        export(
            path,
            tmp_path / "out",
            "parquet",
            observations=["/odom"],
            actions=["/speed"],
            provenance={},
        )


def handmade_record(path: Path, entries: list[tuple[str, str, str | None, int, dict]]) -> Path:
    """An MCAP record of (topic, type, side, log time, value), with labd.side where side is given."""
    types = TypeRegistry.default()
    graph = Graph(types)
    schemas: dict[str, int] = {}
    channels: dict[tuple[str, str | None], int] = {}
    with path.open("wb") as stream:
        writer = McapWriter(stream)
        writer.start(profile="ros2")
        for topic, type_name, side, time, value in entries:
            if type_name not in schemas:
                text = types.definition_text(type_name).encode()
                schemas[type_name] = writer.register_schema(type_name, "ros2msg", text)
            if (topic, side) not in channels:
                metadata = {} if side is None else {"labd.side": side}
                channels[topic, side] = writer.register_channel(
                    topic, "cdr", schemas[type_name], metadata
                )
            data = graph.message(type_name, value).cdr()
            writer.add_message(channels[topic, side], time, data, time)
        writer.finish()
    return path


def sided_entries(
    lab: str | None, client: str | None
) -> list[tuple[str, str, str | None, int, dict]]:
    """Tick 0 and 1 of a drive where a client wrote on /odom and the lab on /cmd_vel."""
    odom, twist, episode = (
        "nav_msgs/msg/Odometry",
        "geometry_msgs/msg/Twist",
        "lab_msgs/msg/Episode",
    )

    def at(x: float) -> dict:
        return {"pose": {"pose": {"position": {"x": x}}}}

    return [
        ("/odom", odom, lab, 0, at(1.0)),
        ("/odom", odom, client, 0, at(42.0)),
        ("/lab/episode", episode, lab, 0, {"task": TASK, "tick": 0, "status": "running"}),
        ("/cmd_vel", twist, client, 0, {"linear": {"x": 0.5}}),
        ("/cmd_vel", twist, lab, 0, {"linear": {"x": 9.0}}),
        ("/odom", odom, lab, 100_000_000, at(2.0)),
        ("/lab/episode", episode, lab, 100_000_000, {"task": TASK, "tick": 1, "status": "running"}),
    ]


def test_observations_are_the_labs_and_actions_the_clients(tmp_path):
    """Channels of the other side on a named topic are not read: no client observation, no lab action."""
    sided = handmade_record(tmp_path / "sided.mcap", sided_entries("lab", "client"))
    rows = pq.read_table(
        export(
            sided,
            tmp_path / "a",
            "parquet",
            observations=["/odom"],
            actions=["/cmd_vel"],
            provenance={},
        ).files[0]
    ).to_pylist()
    assert [
        (r["observation./odom.pose.pose.position.x"], r["action./cmd_vel.linear.x"]) for r in rows
    ] == [(1.0, 0.5)]
    old = handmade_record(tmp_path / "old.mcap", sided_entries(None, None))
    rows = pq.read_table(
        export(
            old,
            tmp_path / "b",
            "parquet",
            observations=["/odom"],
            actions=["/cmd_vel"],
            provenance={},
        ).files[0]
    ).to_pylist()
    assert [
        (r["observation./odom.pose.pose.position.x"], r["action./cmd_vel.linear.x"]) for r in rows
    ] == [(42.0, 9.0)]  # a record without sides is read by topic alone
