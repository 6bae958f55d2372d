"""A record's summary for its page: plots, camera thumbnails, the maze's map, the 3D scene.

The records are made as a trial makes them: the task's robot on a graph, a client
node publishing commands and stepping in lockstep, the recorder with the manifest and
the model as attachments (as ``labd.trial.LabTrial`` files them).
"""

from __future__ import annotations

import base64
import gzip
import io
import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import mujoco
import numpy as np
import orjson
import pytest
from PIL import Image

from labd.errors import SummaryError
from labd.graph.graph import Graph, Side
from labd.graph.types import TypeRegistry
from labd.recorder import Recorder
from labd.recorder import series as S
from labd.recorder.summary import MAX_POINTS, VERSION, decode, summarize, summary_blob
from labd.sim.robot import Robot
from repository.digests import canonical_json
from tests.helpers.manifests import of_robot
from tests.labd.test_recorder import digest_topics, step

Command = tuple[str, str, dict[str, Any]]  # topic, type, value


@dataclass
class Drive:
    path: Path
    robot: Robot
    truth: list[tuple[float, float]] = field(default_factory=list)  # world x, y per tick
    objects: list[dict[str, np.ndarray]] = field(default_factory=list)  # per tick


def drive(
    registry: TypeRegistry,
    folder: Path,
    task: str,
    ticks: int,
    commands: Callable[[int], list[Command]],
    *,
    camera: bool = False,
    params: dict[str, Any] | None = None,
    seed: int = 3,
) -> Drive:
    """Record ``ticks`` lockstep ticks of ``task``, the client sending ``commands(tick)``."""
    graph = Graph(registry, name="summary-test")
    robot = Robot(graph, task, params or {}, seed)
    manifest = of_robot(robot, seed)
    recorder = Recorder(graph, folder, digest_topics=digest_topics(robot), manifest=manifest)
    client = graph.create_node("/controller", side=Side.CLIENT)
    if camera:
        client.subscribe("/camera/image/compressed", None, lambda m: None)
    made = Drive(folder / "trial.mcap", robot)
    publishers: dict[str, Any] = {}
    physics = robot.sim.physics
    try:
        robot.publish()
        made.truth.append(_base(physics))
        for tick in range(ticks):
            for topic, kind, value in commands(tick):
                if topic not in publishers:
                    publishers[topic] = client.advertise(topic, kind)
                publishers[topic].publish(value)
            step(client)
            made.truth.append(_base(physics))
    finally:
        sim = robot.sim
        files = {"model.xml": ("application/xml", sim.model_xml().encode())}
        for name, data in sim.task.model_assets.items():
            files[f"model/{name}"] = ("application/octet-stream", data)
        files["manifest.json"] = ("application/json", canonical_json(manifest).encode())
        recorder.finish(attachments=files)
    return made


def _base(physics: Any) -> tuple[float, float]:
    x, y = physics.named.data.xpos[1][:2]
    return float(x), float(y)


def twist(v: float, w: float) -> Command:
    return ("/cmd_vel", "geometry_msgs/msg/Twist", {"linear": {"x": v}, "angular": {"z": w}})


@pytest.fixture(scope="module")
def maze(registry, tmp_path_factory) -> Iterator[Drive]:
    """60 ticks of the maze with the camera on: ahead, then a turn, then slowly ahead
    (never into a wall, where wheels slip and odometry drifts)."""
    folder = tmp_path_factory.mktemp("maze")

    def commands(tick: int) -> list[Command]:
        if tick < 20:
            return [twist(0.3, 0.0)]
        return [twist(0.0, 1.0 + tick / 100) if tick < 35 else twist(0.08, 0.0)]

    made = drive(registry, folder, "icreate-maze", 60, commands, camera=True)
    yield made
    made.robot.close()  # its rendering context, now rather than at some later collection


@pytest.fixture(scope="module")
def maze_summary(maze, registry) -> dict[str, Any]:
    return summarize(maze.path, types=registry)


def plot(summary: dict[str, Any], topic: str, group: str) -> dict[str, list[Any]]:
    found = [p for p in summary["plots"] if p["topic"] == topic and p["group"] == group]
    assert found, [(p["topic"], p["group"]) for p in summary["plots"]]
    return dict(zip(found[0]["labels"], found[0]["values"], strict=True))


def test_points_are_the_ticks_with_their_times(maze_summary):
    """A short record keeps every tick: tick 0 and 60 more, at the 10 Hz control period."""
    assert maze_summary["version"] == VERSION and maze_summary["task"] == "icreate-maze"
    assert maze_summary["tick"] == list(range(61))
    assert maze_summary["t"] == pytest.approx([k / 10 for k in range(61)], abs=1e-6)
    assert maze_summary["duration"] == pytest.approx(6.0)


def test_observations_plot_by_field_and_commands_at_the_tick_they_answer(maze_summary):
    """/odom's pose reads as x, y and yaw; the command the controller sent after seeing
    tick k is plotted at tick k; reward comes first; fields that never change are listed
    apart instead of drawn."""
    summary = maze_summary
    assert summary["plots"][0]["topic"] == "/lab/episode"
    pose = plot(summary, "/odom", "pose")
    assert set(pose) == {"position.x", "position.y", "orientation.yaw"}
    assert pose["position.x"][0] == 0 and pose["position.x"][20] > 0.3
    turn = plot(summary, "/cmd_vel", "angular")["z"]
    assert turn[:20] == [0] * 20
    assert turn[20:35] == pytest.approx([1.0 + k / 100 for k in range(20, 35)], abs=1e-3)
    assert turn[35:] == [0] * 26
    assert plot(summary, "/cmd_vel", "linear")["x"][34:36] == [0, 0.08]
    sides = {p["topic"]: p["side"] for p in summary["plots"]}
    assert sides["/cmd_vel"] == "client" and sides["/odom"] == "lab"
    assert ["/cmd_vel", "linear", "y", 0.0] in summary["constant"]
    assert set(plot(summary, "/joint_states", "position")) == {
        "left_wheel_joint",
        "right_wheel_joint",
    }


def test_camera_frames_are_one_sprite_of_thumbnails(maze, maze_summary):
    """Each recorded frame is a thumbnail, in time order, in one JPEG."""
    camera = maze_summary["camera"]
    assert camera["source"] == [320, 240]
    assert len(camera["t"]) == 62  # the subscriber's first frame, tick 0, 60 ticks
    assert camera["t"] == sorted(camera["t"])
    header, data = camera["sprite"].split(",", 1)
    assert header == "data:image/jpeg;base64"
    sprite = Image.open(io.BytesIO(base64.b64decode(data)))
    rows = math.ceil(len(camera["t"]) / camera["columns"])
    assert sprite.size == (camera["columns"] * camera["width"], rows * camera["height"])
    assert camera["width"] / camera["height"] == pytest.approx(320 / 240, rel=0.02)


def test_the_map_has_the_mazes_walls_tags_and_goal_in_odom(maze, maze_summary):
    """The map, from the record's model, matches the maze the task drew: its tags by id
    and place, the goal cell, walls all round; the path starts at odom's origin."""
    task = maze.robot.sim.task
    found = maze_summary["map"]
    assert found["frame"] == "odom"
    tags = {int(t[0]): (t[1], t[2]) for t in found["tags"]}
    assert set(tags) == {t.id for t in task.tags}
    for tag in task.tags:
        assert tags[tag.id] == pytest.approx(task.to_odom(*tag.centre[:2]), abs=2e-3)
    gx, gy = task.goal_odom
    x0, y0, x1, y1 = found["goal"]
    assert x0 < gx < x1 and y0 < gy < y1
    assert len(found["walls"]) > 4
    path = found["path"]
    assert (path["x"][0], path["y"][0]) == (0, 0)
    assert path["t"] == sorted(path["t"]) and len(path["x"]) > 10


def test_the_scene_puts_the_robot_where_the_simulation_had_it(maze, maze_summary):
    """Posing the model with the scene's joint positions (as the page does, by forward
    kinematics) puts the robot's body where the physics had it, to odometry's drift."""
    scene = maze_summary["scene"]
    sim = maze.robot.sim
    model = mujoco.MjModel.from_xml_string(sim.model_xml(), sim.task.model_assets)
    data = mujoco.MjData(model)
    body = model.body("base_link").id
    for k in (0, 20, 40, 60):
        qpos = np.array(scene["qpos0"])
        qpos[scene["moving"]] = scene["qpos"][k]
        data.qpos[:] = qpos
        mujoco.mj_kinematics(model, data)
        assert data.xpos[body][:2] == pytest.approx(maze.truth[k], abs=0.01)
    names = [b["name"] for b in scene["bodies"]]
    assert "base_link" in names and {g["shape"] for g in scene["geoms"]} >= {"box", "cylinder"}
    tag_textures = [g for g in scene["geoms"] if g["shape"] == "plane" and "texture" in g]
    assert len(tag_textures) >= len(maze.robot.sim.task.tags)


def test_the_pr2s_arms_and_objects_are_posed_from_the_record(registry, tmp_path, request):
    """/joint_states pose the arm's joints, /tf the base, /objects the objects: the scene
    at each point matches the simulation's joints and objects."""
    ready = [0.66, -0.18, 1.34, -1.65, 1.37, -1.78, 2.1]

    def commands(tick: int) -> list[Command]:
        if tick == 0:
            points = [{"positions": ready, "time_from_start": {"sec": 2, "nanosec": 0}}]
            names = [f"l_{j}_joint" for j in ("shoulder_pan", "shoulder_lift", "upper_arm_roll",
                     "elbow_flex", "forearm_roll", "wrist_flex", "wrist_roll")]  # fmt: skip
            return [
                ("/left_arm/command", "trajectory_msgs/msg/JointTrajectory",
                 {"joint_names": names, "points": points}),
                ("/base/cmd_vel", "geometry_msgs/msg/Twist", {"linear": {"y": 0.1}}),
            ]  # fmt: skip
        return []

    made = drive(registry, tmp_path, "pr2-table", 40, commands)
    request.addfinalizer(made.robot.close)
    summary = summarize(made.path, types=registry)
    scene = summary["scene"]
    model = made.robot.sim.physics.model
    elbow = model.joint("l_elbow_flex_joint")
    assert int(elbow.qposadr[0]) in scene["moving"]
    last = np.array(scene["qpos0"])
    last[scene["moving"]] = scene["qpos"][-1]
    physics = made.robot.sim.physics
    assert last[elbow.qposadr[0]] == pytest.approx(physics.data.qpos[elbow.qposadr[0]], abs=1e-3)
    base_y = model.joint("base_y_joint").qposadr[0]
    assert last[base_y] == pytest.approx(physics.data.qpos[base_y], abs=1e-3)
    for item in made.robot.sim.task.plan.things:
        adr = model.joint(item.name).qposadr[0]
        assert last[adr : adr + 3] == pytest.approx(physics.data.qpos[adr : adr + 3], abs=2e-3)
    # sent once, before the first step: a target that never changed
    assert ["/left_arm/command", "target", "l_elbow_flex_joint", -1.65] in summary["constant"]
    assert summary["camera"] is None and summary["map"] is None


def test_a_long_record_is_decimated_keeping_its_spikes():
    """Each bucket keeps its value farthest from its mean: a one-tick spike survives."""
    values = np.zeros(3001)
    values[1234] = 10.0
    values[2000:] = np.nan
    starts = S.buckets(len(values), MAX_POINTS)
    kept = S.decimate(values, starts)
    assert len(kept) == MAX_POINTS and np.nanmax(kept) == 10.0
    assert np.isnan(kept[-1]) and S.rounded(kept)[-1] is None
    assert S.rounded(np.array([0.123456, 1.0])) == [0.1235, 1]  # a 1000th of the range


def test_flatten_follows_the_conventions(registry):
    """Quaternions read as roll, pitch, yaw; joint states by name; sequences by count."""
    store = registry.typestore
    Quaternion = store.types["geometry_msgs/msg/Quaternion"]
    Pose = store.types["geometry_msgs/msg/Pose"]
    Point = store.types["geometry_msgs/msg/Point"]
    yaw = 0.7
    pose = Pose(Point(1.0, 2.0, 0.0), Quaternion(0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2)))
    flat = S.flatten(pose)
    assert flat[("position", "x")] == 1.0 and flat[("orientation", "yaw")] == pytest.approx(yaw)
    Header = store.types["std_msgs/msg/Header"]
    Time = store.types["builtin_interfaces/msg/Time"]
    none_seen = store.types["lab_msgs/msg/ArTagArray"](Header(Time(0, 0), "camera"), [])
    assert S.flatten(none_seen) == {("", "tags.count"): 0.0}  # seen nothing: 0, not a gap


def test_the_stored_summary_fits_its_budget_and_reads_back(maze, registry):
    """The stored form is gzip'd JSON of the same summary, under its budget."""
    blob = summary_blob(maze.path, types=registry)
    assert blob[:2] == b"\x1f\x8b"
    value = decode(blob)
    assert value == orjson.loads(gzip.decompress(blob)) and value["version"] == VERSION
    assert len(blob) <= max(16 * 1024, maze.path.stat().st_size // 12)


def test_a_summary_past_its_time_stops(maze, registry):
    """Summarizing stops with SummaryError once past its time, rather than running on."""
    with pytest.raises(SummaryError, match="took longer than"):
        summarize(maze.path, types=registry, seconds=-1)


def test_a_damaged_record_is_a_summary_error(tmp_path, registry):
    bad = tmp_path / "trial.mcap"
    bad.write_bytes(b"\x89MCAP0\r\n" + b"\x00" * 64)
    with pytest.raises(SummaryError, match="could not be read"):
        summarize(bad, types=registry)
