"""icreate-maze: the maze, driving, bumpers, clipping, tags, the camera and success."""

from __future__ import annotations

import io
import itertools
import math

import mujoco
import numpy as np
import pytest
from PIL import Image

from labd.errors import MessageError, ParamError
from labd.sim.base import stamp_of
from labd.sim.icreate import maze
from labd.sim.icreate.layout import CELL, DIRECTIONS, STEPS, Layout
from labd.sim.icreate.model import MAX_TURN_RATE, MAX_WHEEL_SPEED
from labd.sim.simulation import Simulation
from repository.trial import EpisodeStatus

TASK = "icreate-maze"


def twist(linear: float = 0.0, angular: float = 0.0) -> dict:
    return {
        "linear": {"x": linear, "y": 0.0, "z": 0.0},
        "angular": {"x": 0.0, "y": 0.0, "z": angular},
    }


def observe(sim: Simulation, topic: str) -> dict:
    data = sim.task.observe(sim.physics, topic, stamp_of(sim.physics))
    assert data is not None
    return data


def drive(sim: Simulation, ticks: int, linear: float = 0.0, angular: float = 0.0) -> None:
    sim.task.command("/cmd_vel", twist(linear, angular))
    for _ in range(ticks):
        sim.step()


def place(sim: Simulation, x: float, y: float, yaw: float) -> None:
    """Put the robot at rest at (x, y) facing ``yaw`` (world frame)."""
    physics = sim.physics
    physics.named.data.qpos["base"] = [x, y, 0.0, math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)]
    physics.named.data.qvel["base"] = 0.0
    physics.forward()


def yaw_of(quaternion: dict) -> float:
    return 2 * math.atan2(quaternion["z"], quaternion["w"])


@pytest.fixture
def sim() -> Simulation:
    return Simulation(TASK, {}, seed=3)


def test_maze_is_solvable_and_depends_on_the_seed():
    """Every seed gives a maze with a path from start to a distinct goal; seeds differ."""
    grids = set()
    for seed in range(12):
        layout = Layout.generate(9, 2, np.random.default_rng(seed))
        path = layout.path(layout.start)
        assert layout.start != layout.goal
        assert path[0] == layout.start and path[-1] == layout.goal
        assert all(layout.grid[cell] for cell in path)
        assert all(abs(a[0] - b[0]) + abs(a[1] - b[1]) == 1 for a, b in itertools.pairwise(path))
        grids.add(layout.text())
    assert len(grids) == 12


def test_same_seed_same_model_and_another_seed_another():
    """The compiled model XML is a function of the seed and parameters."""
    first = Simulation(TASK, {}, seed=4).model_xml()
    assert first == Simulation(TASK, {}, seed=4).model_xml()
    assert first != Simulation(TASK, {}, seed=5).model_xml()
    assert first.count('<geom name="wall') < 60  # runs of wall cells are merged


def test_parameters_are_validated():
    """An even maze size or an unknown parameter is refused with the valid list."""
    with pytest.raises(ParamError, match="must be odd"):
        Simulation(TASK, {"maze_size": 10})
    with pytest.raises(ParamError) as info:
        Simulation(TASK, {"maze_sise": 9})
    assert "maze_size" in str(info.value) and "control_rate" in str(info.value)


def test_driving_forward_moves_odometry_as_commanded(sim):
    """Forward at 0.3 m/s for 1.5 s: odometry x grows by about 0.45 m with no y or yaw drift."""
    drive(sim, 15, linear=0.3)
    odom = observe(sim, "/odom")
    pose, speed = odom["pose"]["pose"], odom["twist"]["twist"]["linear"]["x"]
    assert odom["header"]["frame_id"] == "odom" and odom["child_frame_id"] == "base_link"
    assert pose["position"]["x"] == pytest.approx(0.45, abs=0.03)
    assert abs(pose["position"]["y"]) < 1e-6 and abs(yaw_of(pose["orientation"])) < 1e-6
    assert speed == pytest.approx(0.3, abs=0.01)
    # The robot truly moved that far along its start heading (odometry does not lie here).
    x, y, _ = sim.physics.base_pose()
    assert sim.task.to_odom(x, y) == pytest.approx((pose["position"]["x"], 0.0), abs=0.01)
    tf = observe(sim, "/tf")["transforms"][0]
    assert tf["transform"]["translation"]["x"] == pose["position"]["x"]


def test_turning_in_place_turns(sim):
    """1 rad/s for 1.5 s turns the robot by about 1.4 rad, left, without leaving its spot."""
    drive(sim, 15, angular=1.0)
    pose = observe(sim, "/odom")["pose"]["pose"]
    assert yaw_of(pose["orientation"]) == pytest.approx(1.4, abs=0.1)
    assert math.hypot(pose["position"]["x"], pose["position"]["y"]) < 0.01
    _, _, yaw = sim.physics.base_pose()
    assert math.remainder(yaw - sim.task.start[2], math.tau) == pytest.approx(1.4, abs=0.1)


def facing_wall(layout: Layout, open_right: bool = False) -> tuple[tuple[int, int], int]:
    """The first floor cell (row-major, not the goal) with a wall on one side, and that side;
    with ``open_right``, the side clockwise of it must be open."""
    for i, j in np.argwhere(layout.grid).tolist():
        for k, (di, dj) in enumerate(STEPS):
            ri, rj = STEPS[(k + 1) % 4]
            if (
                (i, j) != layout.goal
                and not layout.grid[i + di, j + dj]
                and (layout.grid[i + ri, j + rj] or not open_right)
            ):
                return (i, j), k
    raise AssertionError("no wall")


def test_driving_into_a_wall_presses_both_bumpers_once(sim):
    """Head-on into a wall: both bumpers press, one collision is counted, the robot stops."""
    cell, side = facing_wall(sim.task.layout)
    x, y = sim.task.layout.centre(cell)
    dx, dy = DIRECTIONS[side]
    place(sim, x, y, math.atan2(dy, dx))
    assert observe(sim, "/bumper")["left"] is False
    assert sim.task.metrics(sim.physics)["collisions"] == 0
    drive(sim, 30, linear=0.3)
    bumper = observe(sim, "/bumper")
    assert bumper["left"] and bumper["right"]
    assert sim.task.metrics(sim.physics)["collisions"] == 1
    gap = CELL / 2 - abs(
        (sim.physics.base_pose()[0] - x) * dx + (sim.physics.base_pose()[1] - y) * dy
    )
    assert gap == pytest.approx(0.17, abs=0.01)  # the shell's radius: against the wall


def test_a_wall_to_the_front_left_presses_the_left_bumper_only(sim):
    """A contact 45 degrees left of dead ahead presses the left bumper, not the right."""
    cell, side = facing_wall(sim.task.layout, open_right=True)
    x, y = sim.task.layout.centre(cell)
    dx, dy = DIRECTIONS[side]
    place(sim, x, y, math.atan2(dy, dx) - math.pi / 4)
    sim.task.command("/cmd_vel", twist(0.2))
    for _ in range(40):
        sim.step()
        bumper = observe(sim, "/bumper")
        if bumper["left"] or bumper["right"]:
            break
    assert bumper["left"] and not bumper["right"]


def test_out_of_range_commands_are_clipped_and_counted(sim):
    """Speeds past the robot's limits are clipped (turn radius kept) and each message counted."""
    sim.task.command("/cmd_vel", twist(2.0))
    assert sim.task.action(sim.physics).tolist() == [MAX_WHEEL_SPEED, MAX_WHEEL_SPEED]
    sim.task.command("/cmd_vel", twist(0.2, -1.0))
    assert sim.task.metrics(sim.physics)["clipped_commands"] == 1
    sim.task.command("/cmd_vel", twist(0.0, 10.0))
    assert sim.task.action(sim.physics) == pytest.approx([-MAX_WHEEL_SPEED, MAX_WHEEL_SPEED])
    sim.task.command("/cmd_vel", twist(0.5, 2.0))  # each within its limit, not together
    left, right = sim.task.action(sim.physics)
    assert right == pytest.approx(MAX_WHEEL_SPEED) and (right - left) / (right + left) == (
        pytest.approx(2.0 * 0.235 / 2 / 0.5)
    )
    assert sim.task.metrics(sim.physics)["clipped_commands"] == 3
    assert pytest.approx(4.255, abs=0.001) == MAX_TURN_RATE


def test_nan_and_infinity_are_refused_naming_the_field(sim):
    """A NaN or infinite speed is refused with the field's name; the last command stands."""
    sim.task.command("/cmd_vel", twist(0.2))
    with pytest.raises(MessageError, match=r"linear\.x must be a finite number"):
        sim.task.command("/cmd_vel", twist(math.nan))
    bad = twist(0.1)
    bad["angular"]["y"] = math.inf
    with pytest.raises(MessageError, match=r"angular\.y"):
        sim.task.command("/cmd_vel", bad)
    assert sim.task.action(sim.physics) == pytest.approx([0.2, 0.2])


def look_at(sim: Simulation, tag_index: int, back: float = 0.0, turn: float = 0.0) -> None:
    """Stand in front of a tag (``back`` metres further away), facing it (turned by ``turn``)."""
    tag = sim.task.tags[tag_index]
    x, y = (tag.centre + (CELL / 2 + back) * tag.normal)[:2]
    place(sim, float(x), float(y), math.atan2(-tag.normal[1], -tag.normal[0]) + turn)


def test_ar_tags_reports_a_tag_in_view_where_the_camera_sees_it(sim):
    """Facing a tag: it is reported at the pixel Camera.project gives, with its pose and size."""
    look_at(sim, 0)
    tag = sim.task.tags[0]
    message = observe(sim, "/ar_tags")
    assert message["header"]["frame_id"] == "camera_optical_frame"
    found = {t["id"]: t for t in message["tags"]}
    seen = found[tag.id]
    camera = sim.task.camera
    ((u, v),) = camera.project(sim.physics, camera.to_optical(sim.physics, tag.centre[None]))
    assert (seen["cx"], seen["cy"]) == pytest.approx((u, v), abs=1e-6)
    assert (u, v) == pytest.approx(camera.center(), abs=1.0)  # straight ahead, camera height
    focal = camera.focal(sim.physics)
    assert seen["distance"] == pytest.approx(CELL / 2 - 0.12 - 0.001, abs=1e-3)
    assert seen["width"] == pytest.approx(focal * 0.16 / seen["distance"], rel=0.01)
    assert seen["pose"]["orientation"]["w"] == pytest.approx(1.0, abs=1e-6)
    assert seen["pose"]["position"]["z"] == pytest.approx(seen["distance"], abs=1e-6)


def test_ar_tags_ignores_a_tag_behind_a_wall_or_out_of_view(sim):
    """A tag that would be in the image but has a wall in front of it is not reported."""
    detector = sim.task.detector
    clear = detector._unoccluded
    blocked = None
    layout = sim.task.layout
    for cell in np.argwhere(layout.grid).tolist():
        for k in range(8):
            place(sim, *layout.centre((cell[0], cell[1])), k * math.pi / 4)
            detector._unoccluded = lambda physics, eye, tags: np.ones(len(tags), dtype=bool)
            unchecked = {t["id"] for t in detector.detect(sim.physics)}
            detector._unoccluded = clear
            checked = {t["id"] for t in observe(sim, "/ar_tags")["tags"]}
            assert checked <= unchecked
            if unchecked - checked:
                blocked = next(iter(unchecked - checked))
                break
        if blocked is not None:
            break
    assert blocked is not None, "no occluded tag in this maze"
    # Confirm independently: a ray from the camera toward the tag meets a wall first.
    tag = next(t for t in sim.task.tags if t.id == blocked)
    eye = sim.physics.named.data.cam_xpos["front"]
    hits = []
    for target in [tag.centre, *(tag.centre + 0.9 * (tag.corners - tag.centre))]:
        ray = target - eye
        geom = np.zeros(1, dtype=np.int32)
        group = np.array([1, 0, 0, 0, 0, 0], dtype=np.uint8)
        hit = mujoco.mj_ray(
            sim.physics.model.ptr,
            sim.physics.data.ptr,
            eye,
            ray / np.linalg.norm(ray),
            group,
            1,
            -1,
            geom,
        )
        hits.append(0 <= hit < np.linalg.norm(ray) - 0.001)
        if hits[-1]:
            assert sim.physics.model.geom(int(geom[0])).name.startswith("wall")
    assert any(hits)
    # Turned away, the tag in front is out of view.
    look_at(sim, 0, turn=math.pi / 2)
    assert sim.task.tags[0].id not in {t["id"] for t in observe(sim, "/ar_tags")["tags"]}


def test_a_scripted_policy_reaches_the_goal(sim):
    """Following the shortest path on the true pose reaches the goal cell: success, with bonus."""
    layout = sim.task.layout
    goal = observe(sim, "/goal")
    assert (goal["point"]["x"], goal["point"]["y"]) == pytest.approx(
        sim.task.to_odom(*layout.centre(layout.goal))
    )
    while sim.running:
        x, y, yaw = sim.physics.base_pose()
        path = layout.path(layout.cell_at(x, y))
        tx, ty = layout.centre(path[1] if len(path) > 1 else path[0])
        error = math.remainder(math.atan2(ty - y, tx - x) - yaw, math.tau)
        speed = 0.0 if abs(error) > 0.5 else 0.45 * math.cos(error)
        sim.task.command("/cmd_vel", twist(speed, 3.0 * error))
        sim.step()
    assert sim.status is EpisodeStatus.SUCCEEDED
    assert "reached the goal cell" in sim.reason
    metrics = sim.metrics()
    assert metrics["success"] is True
    assert metrics["reward"] == pytest.approx(sim.total_reward)
    assert metrics["reward"] > maze.SUCCESS_BONUS
    assert metrics["distance_to_goal"] < CELL / 2 * math.sqrt(2)
    start, end = sim.task.start[:2], sim.physics.base_pose()[:2]
    assert (
        math.dist(start, end)
        <= metrics["path_length"]
        < 1.5 * len(layout.path(layout.start)) * CELL
    )
    odom = observe(sim, "/odom")["pose"]["pose"]["position"]
    assert math.hypot(odom["x"] - goal["point"]["x"], odom["y"] - goal["point"]["y"]) < CELL


def test_camera_image_is_a_jpeg_of_the_requested_size(sim):
    """The image topic carries a JPEG that decodes to 320 x 240, with matching camera_info."""
    image = observe(sim, "/camera/image/compressed")
    assert image["format"] == "jpeg" and image["header"]["frame_id"] == "camera_optical_frame"
    decoded = Image.open(io.BytesIO(image["data"]))
    assert decoded.format == "JPEG" and decoded.size == (320, 240)
    info = observe(sim, "/camera/camera_info")
    assert (info["width"], info["height"]) == (320, 240)


def test_static_transforms_put_the_optical_frame_looking_ahead(sim):
    """camera_link -> camera_optical_frame turns z ahead, x right and y down, as ROS has it."""
    transforms = observe(sim, "/tf_static")["transforms"]
    assert [t["child_frame_id"] for t in transforms] == ["camera_link", "camera_optical_frame"]
    q = transforms[1]["transform"]["rotation"]
    matrix = np.zeros(9)
    mujoco.mju_quat2Mat(matrix, np.array([q["w"], q["x"], q["y"], q["z"]]))
    columns = matrix.reshape(3, 3).T  # the optical axes in camera_link
    assert columns[2] == pytest.approx([1, 0, 0]) and columns[0] == pytest.approx([0, -1, 0])


def test_same_commands_same_observations(sim):
    """Two episodes with the same seed and commands publish identical messages."""
    other = Simulation(TASK, {}, seed=3)
    for s in (sim, other):
        drive(s, 10, 0.4, 0.7)
        drive(s, 10, -0.2, -1.0)
    for topic in ("/odom", "/joint_states", "/ar_tags", "/bumper"):
        assert observe(sim, topic) == observe(other, topic), topic


def test_a_diverging_physics_fails_the_episode():
    """A NaN in the state ends the episode as failed with a reason, not an exception."""
    sim = Simulation(TASK, {}, seed=1)
    sim.physics.data.qvel[0] = math.nan
    sim.step()
    assert sim.status is EpisodeStatus.FAILED and "diverged" in sim.reason
