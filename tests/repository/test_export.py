"""Exports of real records (icreate-maze, lockstep, the Recorder) to Parquet and LeRobot v3.0:
one row per tick from tick 0, the task's stable layout, every camera image, provenance."""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import av
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from labd.exports import export_records, layout
from labd.graph.graph import Graph, Side
from labd.graph.types import TypeRegistry
from labd.recorder import Recorder
from labd.sim import registry
from labd.sim.robot import Robot
from repository.errors import ExportError
from repository.export import Source, export
from repository.formats import FORMATS, export_format
from repository.lerobot import LEROBOT
from repository.parquet import EPISODES_KEY, PARQUET
from tests.helpers.manifests import trial_manifest

TASK = "icreate-maze"
TICKS = 24
CAMERA = "/camera/image/compressed"
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
    camera: bool | int = True,
    reset_after: int | None = None,
) -> Drive:
    """Drive icreate-maze in lockstep, publishing ``command(k)`` before each step; watch the
    camera from the start (True), never (False), or from the step of that tick (an int)."""
    graph = Graph(TypeRegistry.default(), name="export-test")
    robot = Robot(graph, TASK, {}, 3)
    task = robot.sim.task
    topics = {o.name for o in task.observations} | {c.name for c in task.commands}
    manifest = trial_manifest(
        TASK,
        registry.get(TASK).version,
        registry.validate(TASK, {}),
        3,
        model_sha256=robot.sim.model_digest(),
        repository=PROVENANCE["repository"],
        commit=PROVENANCE["commit"],
    ).to_json()
    recorder = Recorder(graph, folder, digest_topics=topics, manifest=manifest)
    run = Drive(folder / "trial.mcap")
    latest: dict[str, Any] = {}

    def tap(topic: Any, message: Any, side: Side, sender: Any) -> None:
        latest[topic.name] = message.data
        if topic.name == "/lab/episode":
            run.observed.append(dict(latest))
            run.episodes.append(message.data)

    graph.taps.append(tap)
    client = graph.create_node("/controller", side=Side.CLIENT)
    if camera is True:
        client.subscribe(CAMERA, None, lambda message: None)
    cmd_vel = client.advertise("/cmd_vel", "geometry_msgs/msg/Twist")
    held: dict[str, Any] = {}
    try:
        robot.publish()
        for tick in range(ticks):
            if camera is not True and camera is not False and tick == camera:
                client.subscribe(CAMERA, None, lambda message: None)
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


def known(trial: int = 7) -> dict[str, Any]:
    """What the archive knows of a record: its trial and digests."""
    return {"trial": trial, "kind": "trial", "data_digest": "cd" * 32, "outcome": "fail"}


def rows_of(path: Path) -> list[dict[str, Any]]:
    return pq.read_table(path).to_pylist()


# -- one row per tick --------------------------------------------------------------------------


def test_parquet_has_a_row_per_tick_from_tick_0_with_neutral_commands_first(tmp_path):
    """Ticks before the controller's first command have rows too, with the neutral command
    (standing still); each row pairs tick k's observations with the command of step k."""
    run = drive(tmp_path / "trial", first_command=3)
    summary = export_records([(run.mcap, known())], tmp_path / "out", PARQUET)
    assert (summary.frames, summary.episodes) == (TICKS, 1)  # the last tick has no step
    rows = rows_of(summary.files[0])
    assert [r["frame_index"] for r in rows] == [r["index"] for r in rows] == list(range(TICKS))
    assert [r["timestamp"] for r in rows] == pytest.approx([k / 10 for k in range(TICKS)])
    for k, row in enumerate(rows):
        sent = run.sent[k] or {"linear": {"x": 0.0}, "angular": {"z": 0.0}}
        assert row["action.cmd_vel.linear.x"] == pytest.approx(sent["linear"]["x"])
        assert row["action.cmd_vel.angular.z"] == pytest.approx(sent["angular"]["z"])
        seen = run.observed[k]
        position = seen["/odom"]["pose"]["pose"]["position"]
        assert row["observation.odom.x"] == pytest.approx(position["x"])
        assert row["observation.bumper.left"] == float(seen["/bumper"]["left"])
        assert row["observation.goal.x"] == pytest.approx(seen["/goal"]["point"]["x"])
        velocity = seen["/joint_states"]["velocity"][
            seen["/joint_states"]["name"].index("right_wheel_joint")
        ]
        assert row["observation.wheel.right.velocity"] == pytest.approx(velocity)
        assert row["observation.images.camera"] == bytes(seen[CAMERA]["data"])
        assert row["next.reward"] == pytest.approx(run.episodes[k + 1]["reward"])
        assert row["task"] == "drive to the goal cell" and row["trial"] == 7
    assert rows[0]["action.cmd_vel.linear.x"] == 0.0
    assert len({r["observation.odom.x"] for r in rows}) > TICKS // 2  # it moved


def test_a_command_holds_when_the_controller_sent_none(tmp_path):
    """Before steps without a new /cmd_vel, the action is the previous command."""
    run = drive(tmp_path / "trial")
    rows = rows_of(export_records([(run.mcap, known())], tmp_path / "out", PARQUET).files[0])
    for k in range(2, TICKS, 4):
        assert rows[k]["action.cmd_vel.linear.x"] == pytest.approx(command(k - 1)["linear"]["x"])


def test_every_row_has_its_camera_image_rendered_where_the_record_has_none(tmp_path):
    """A controller that subscribed after tick 5 (or never) still gets an image on every row,
    rendered by replaying the record: the very JPEG the lab records at that tick."""
    watched = drive(tmp_path / "watched")
    late = drive(tmp_path / "late", camera=5)
    never = drive(tmp_path / "never", camera=False)
    images = {}
    for name, run in (("watched", watched), ("late", late), ("never", never)):
        summary = export_records([(run.mcap, known())], tmp_path / f"out-{name}", PARQUET)
        assert summary.rendered == {"watched": 0, "late": 6, "never": TICKS}[name]
        images[name] = [r["observation.images.camera"] for r in rows_of(summary.files[0])]
    assert images["watched"] == images["late"] == images["never"]
    assert all(image[:2] == b"\xff\xd8" for image in images["never"])


def test_exports_of_different_controllers_have_one_layout_and_merge(tmp_path):
    """Two records whose controllers used different topics (one sent no command at all)
    export the task's same columns, and export together as two episodes, each with its
    provenance."""
    moving = drive(tmp_path / "a", ticks=8, camera=False)
    idle = drive(tmp_path / "b", ticks=6, first_command=99, camera=False)
    a = export_records([(moving.mcap, known(1))], tmp_path / "one", PARQUET)
    b = export_records([(idle.mcap, known(2))], tmp_path / "two", PARQUET)
    assert pq.read_schema(a.files[0]).names == pq.read_schema(b.files[0]).names
    assert a.observation_names == tuple(e.name for e in layout(TASK).observation)
    both = export_records(
        [(moving.mcap, known(1)), (idle.mcap, known(2))], tmp_path / "both", PARQUET
    )
    rows = rows_of(both.files[0])
    assert [r["episode_index"] for r in rows] == [0] * 8 + [1] * 6
    assert [r["frame_index"] for r in rows] == [*range(8), *range(6)]
    assert {r["action.cmd_vel.linear.x"] for r in rows[8:]} == {0.0}
    provenance = json.loads(pq.read_schema(both.files[0]).metadata[EPISODES_KEY.encode()])
    assert [p["trial"] for p in provenance] == [1, 2]
    assert provenance[0]["commit"] == PROVENANCE["commit"]
    assert provenance[0]["manifest_digest"] and provenance[0]["seed"] == 3


def test_a_reset_starts_a_new_episode(tmp_path):
    """A record with two episodes exports two, each numbered from frame 0."""
    run = drive(tmp_path / "trial", ticks=9, camera=False, reset_after=5)
    blind = dataclasses.replace(layout(TASK), cameras=())
    summary = export([Source(run.mcap, {"trial": 1})], tmp_path / "out", PARQUET, blind)
    assert (summary.frames, summary.episodes) == (9, 2)
    rows = rows_of(summary.files[0])
    assert [r["episode_index"] for r in rows] == [0] * 5 + [1] * 4
    assert [r["frame_index"] for r in rows] == [0, 1, 2, 3, 4, 0, 1, 2, 3]
    assert rows[5]["action.cmd_vel.linear.x"] == pytest.approx(command(5)["linear"]["x"])


# -- lerobot ----------------------------------------------------------------------------------


def test_lerobot_v3_layout_video_and_provenance(tmp_path):
    """The v3.0 layout: float32 vectors named as the task's layout, the camera as an AV1
    video with a frame per row, the instruction as the task, each episode's provenance in
    its row of meta/episodes, and nothing of labd's in info.json."""
    first, second = drive(tmp_path / "a", ticks=10), drive(tmp_path / "b", ticks=6, camera=False)
    out = tmp_path / "dataset"
    summary = export_records([(first.mcap, known(1)), (second.mcap, known(2))], out, LEROBOT)
    video = out / "videos" / "observation.images.camera" / "chunk-000" / "file-000.mp4"
    assert sorted(str(p.relative_to(out)) for p in out.rglob("*") if p.is_file()) == [
        "data/chunk-000/file-000.parquet",
        "meta/episodes/chunk-000/file-000.parquet",
        "meta/info.json",
        "meta/labd.json",
        "meta/stats.json",
        "meta/tasks.parquet",
        str(video.relative_to(out)),
    ]
    info = json.loads((out / "meta" / "info.json").read_text())
    assert info["codebase_version"] == "v3.0" and "labd" not in info
    assert (info["fps"], info["total_episodes"], info["total_frames"]) == (10, 2, 16)
    features = info["features"]
    assert features["observation.state"]["names"] == list(summary.observation_names)
    assert features["action"]["names"] == ["cmd_vel.linear.x", "cmd_vel.angular.z"]
    camera = features["observation.images.camera"]
    assert camera["dtype"] == "video" and camera["shape"] == [240, 320, 3]
    assert camera["info"]["video.codec"] == "av1"
    with av.open(str(video)) as container:
        stream = container.streams.video[0]
        assert stream.codec_context.name in ("libdav1d", "av1", "libaom-av1")
        assert sum(1 for _ in container.decode(stream)) == 16

    table = pq.read_table(out / info["data_path"].format(chunk_index=0, file_index=0))
    assert set(table.column_names) == {k for k, f in features.items() if f["dtype"] != "video"}
    vector = table.schema.field("observation.state").type
    assert pa.types.is_fixed_size_list(vector) and vector.value_type == pa.float32()
    state = np.array(table.column("observation.state").to_pylist(), np.float32)
    x = features["observation.state"]["names"].index("odom.x")
    assert state[3, x] == np.float32(first.observed[3]["/odom"]["pose"]["pose"]["position"]["x"])
    assert table.column("frame_index").to_pylist() == [*range(10), *range(6)]
    assert table.column("timestamp").to_pylist() == pytest.approx(
        [k / 10 for k in [*range(10), *range(6)]]
    )
    tasks = pq.read_table(out / "meta" / "tasks.parquet").to_pylist()
    assert tasks == [{"task_index": 0, "task": "drive to the goal cell"}]
    episodes = pq.read_table(out / "meta" / "episodes" / "chunk-000" / "file-000.parquet")
    rows = episodes.to_pylist()
    assert [r["labd/trial"] for r in rows] == [1, 2]
    assert [r["labd/commit"] for r in rows] == [PROVENANCE["commit"]] * 2
    assert rows[1]["videos/observation.images.camera/from_timestamp"] == pytest.approx(1.0)
    assert rows[1]["videos/observation.images.camera/to_timestamp"] == pytest.approx(1.6)
    assert json.loads(rows[0]["labd/provenance"])["data_digest"] == "cd" * 32
    stats = json.loads((out / "meta" / "stats.json").read_text())
    assert np.array(stats["observation.images.camera"]["mean"]).shape == (3, 1, 1)


# -- refusals ---------------------------------------------------------------------------------


def test_an_unknown_format_names_the_formats():
    with pytest.raises(ExportError, match="unknown format 'csv': the formats are parquet, lerobot"):
        export_format("csv")


def test_a_missing_or_unreadable_mcap_is_refused(tmp_path):
    run = drive(tmp_path / "trial", ticks=3, camera=False)
    with pytest.raises(ExportError, match="no MCAP file at"):
        export([Source(tmp_path / "none.mcap", {})], tmp_path / "o1", PARQUET, layout(TASK))
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(run.mcap.read_bytes()[:300])
    with pytest.raises(ExportError, match="not a complete, readable MCAP file"):
        export([Source(cut, {})], tmp_path / "o2", PARQUET, layout(TASK))
    assert not (tmp_path / "o1").exists() and not (tmp_path / "o2").exists()


def test_missing_images_that_nothing_renders_are_refused(tmp_path):
    """Without the lab's renderer, a record lacking a camera's images cannot be exported."""
    run = drive(tmp_path / "trial", ticks=3, camera=False)
    with pytest.raises(ExportError, match=r"no image of camera for 3 ticks \(from tick 0\)"):
        export([Source(run.mcap, {})], tmp_path / "o", PARQUET, layout(TASK))
    assert not (tmp_path / "o").exists()


def test_an_existing_output_and_bad_provenance_are_refused(tmp_path):
    run = drive(tmp_path / "trial", ticks=3, camera=False)
    taken = tmp_path / "taken"
    taken.mkdir()
    (taken / "file").write_text("x")
    with pytest.raises(ExportError, match="already exists"):
        export_records([(run.mcap, known())], taken, PARQUET)
    with pytest.raises(ExportError, match="the provenance must be JSON"):
        export([Source(run.mcap, {"x": object()})], tmp_path / "o", PARQUET, layout(TASK))


def test_the_formats_keep_their_names_in_the_archive():
    """Exports kept beside records are found again under the same names: a format's
    artifact and download names do not change."""
    assert {f.name: (f.artifact, f.filename(12)) for f in FORMATS.values()} == {
        "parquet": ("export.parquet", "trial-12.parquet"),
        "lerobot": ("export-lerobot.zip", "trial-12-lerobot.zip"),
    }
