"""pr2-table: the layout, base, trajectories, clipping, poses, perception, the camera and
a scripted pick-and-place that uses the documented topics only."""

from __future__ import annotations

import io
import math
from typing import Any

import numpy as np
import pytest
from PIL import Image

from labd.errors import MessageError, ParamError
from labd.sim import registry
from labd.sim.base import stamp_of
from labd.sim.pr2 import scene
from labd.sim.simulation import Simulation
from repository.trial import EpisodeStatus

TASK = "pr2-table"
ZERO = {"sec": 0, "nanosec": 0}
LEFT_ARM = [
    f"l_{name}_joint"
    for name in (
        "shoulder_pan",
        "shoulder_lift",
        "upper_arm_roll",
        "elbow_flex",
        "forearm_roll",
        "wrist_flex",
        "wrist_roll",
    )
]
RIGHT_ARM = [name.replace("l_", "r_", 1) for name in LEFT_ARM]
ARMS = {"l": LEFT_ARM, "r": RIGHT_ARM}
SIDES = {"l": "left", "r": "right"}
# Arms over the table, grippers pointing down (the ready pose of the task's documentation).
READY = {
    "l": [0.66, -0.18, 1.34, -1.65, 1.37, -1.78, 2.1],
    "r": [-0.66, -0.18, -1.34, -1.65, -1.37, -1.78, 1.04],
}


def observe(sim: Simulation, topic: str) -> dict:
    data = sim.task.observe(sim.physics, topic, stamp_of(sim.physics))
    assert data is not None
    return data


def seconds(sim: Simulation, duration: float) -> None:
    for _ in range(round(duration / sim.control_timestep)):
        sim.step()


def trajectory(names: list[str], *points: tuple[list[float], float]) -> dict:
    """A JointTrajectory through ``points``: (positions, seconds from its start)."""
    return {
        "header": {"stamp": ZERO, "frame_id": ""},
        "joint_names": names,
        "points": [
            {
                "positions": positions,
                "velocities": [],
                "accelerations": [],
                "effort": [],
                "time_from_start": {"sec": int(at), "nanosec": round(at % 1 * 1e9)},
            }
            for positions, at in points
        ],
    }


def twist(x: float = 0.0, y: float = 0.0, turn: float = 0.0) -> dict:
    return {"linear": {"x": x, "y": y, "z": 0.0}, "angular": {"x": 0.0, "y": 0.0, "z": turn}}


def down(yaw: float) -> dict[str, float]:
    """A tool frame pointing straight down (x along -z), turned ``yaw`` about z."""
    c, s, h = math.cos(yaw / 2), math.sin(yaw / 2), math.sqrt(0.5)
    return {"x": -s * h, "y": c * h, "z": s * h, "w": c * h}  # Rz(yaw) * Ry(90 degrees)


def pose(position: np.ndarray, orientation: dict[str, float], frame: str = "base_footprint"):
    x, y, z = (float(v) for v in position)
    return {
        "header": {"stamp": ZERO, "frame_id": frame},
        "pose": {"position": {"x": x, "y": y, "z": z}, "orientation": orientation},
    }


def transform(sim: Simulation, child: str) -> tuple[np.ndarray, dict[str, float]]:
    """The translation and rotation of ``child`` in its parent frame, from /tf."""
    for item in observe(sim, "/tf")["transforms"]:
        if item["child_frame_id"] == child:
            t = item["transform"]["translation"]
            return np.array([t["x"], t["y"], t["z"]]), item["transform"]["rotation"]
    raise KeyError(child)


def yaw_of(q: dict[str, float]) -> float:
    return math.atan2(2 * (q["w"] * q["z"] + q["x"] * q["y"]), 1 - 2 * (q["y"] ** 2 + q["z"] ** 2))


class PickAndPlace:
    """A scripted controller that moves the goal's object into the target area.

    It uses the topics only (as a controller over the bridge would): /task/goal,
    /objects, /tf and /joint_states in; /torso/command, the arm trajectories and pose
    commands, the gripper commands and /base/cmd_vel out.
    """

    def __init__(self, sim: Simulation) -> None:
        self.sim = sim

    def read(self, topic: str) -> dict:
        return observe(self.sim, topic)

    def send(self, topic: str, data: dict) -> None:
        self.sim.task.command(topic, data)

    def wait(self, done: Any, duration: float) -> bool:
        """Step until ``done()`` holds or ``duration`` seconds pass; whether it held."""
        for _ in range(round(duration / self.sim.control_timestep)):
            if done() or not self.sim.running:
                break
            self.sim.step()
        return bool(done())

    def untuck(self) -> None:
        """Torso up first, then each arm: upper arm raised, turned, lowered to READY,
        so that nothing sweeps across the table."""
        self.send("/torso/command", trajectory(["torso_lift_joint"], ([0.2], 4.0)))
        self.wait(lambda: False, 4.0)
        state = self.read("/joint_states")
        now = dict(zip(state["name"], state["position"], strict=True))
        for side, names in ARMS.items():
            raised = [now[n] for n in names]
            raised[1] = -0.5  # shoulder_lift: upper arm up
            turned = list(READY[side])
            turned[1] = -0.5
            command = trajectory(names, (raised, 2.0), (turned, 4.0), (READY[side], 5.0))
            self.send(f"/{SIDES[side]}_arm/command", command)
        self.wait(lambda: False, 5.5)

    def reach(self, side: str, target: np.ndarray, yaw: float, tolerance: float) -> bool:
        """Tool frame to ``target`` (base_footprint), pointing down; whether it got there."""
        self.send(f"/{SIDES[side]}_arm/pose", pose(target, down(yaw)))
        tool = f"{side}_gripper_tool_frame"
        return self.wait(
            lambda: np.linalg.norm(transform(self.sim, tool)[0] - target) < tolerance, 5.0
        )

    def grip(self, side: str, opening: float, duration: float) -> None:
        self.send(f"/{SIDES[side]}_gripper/command", {"data": opening})
        self.wait(lambda: False, duration)

    def slide_to(self, y: float) -> bool:
        """Drive the base sideways until base_footprint is at odom ``y``."""

        def there() -> bool:
            error = y - transform(self.sim, "base_footprint")[0][1]
            self.send("/base/cmd_vel", twist(y=max(-0.3, min(0.3, 2.0 * error))))
            return abs(error) < 0.003

        arrived = self.wait(there, 10.0)
        self.send("/base/cmd_vel", twist())
        return arrived

    def to_base(self, x: float, y: float, z: float) -> np.ndarray:
        """An odom point in base_footprint (the base only moves in the plane)."""
        (bx, by, _), rotation = transform(self.sim, "base_footprint")
        yaw = yaw_of(rotation)
        dx, dy = x - bx, y - by
        c, s = math.cos(yaw), math.sin(yaw)
        return np.array([c * dx + s * dy, -s * dx + c * dy, z])

    def run(self) -> None:
        goal = self.read("/task/goal")
        table = goal["table_center"]["z"]
        self.untuck()
        seen = {o["name"]: o for o in self.read("/objects")["objects"]}
        target = seen[goal["object"]]
        p, q = target["pose"]["position"], target["pose"]["orientation"]
        side = "l" if p["y"] >= 0 else "r"
        # Close across a box's faces: its yaw modulo 90 degrees, the smallest turn.
        yaw = yaw_of(q) if target["shape"] == "box" else 0.0
        yaw = (yaw + math.pi / 4) % (math.pi / 2) - math.pi / 4
        top = p["z"] + target["size"]["z"] / 2
        grasp = max(top - 0.03, table + 0.025)  # fingertips reach 0.02 m past the tool frame
        self.grip(side, 0.09, 0.2)
        assert self.reach(side, np.array([p["x"], p["y"], top + 0.08]), yaw, 0.01)
        assert self.reach(side, np.array([p["x"], p["y"], grasp]), yaw, 0.005)
        self.grip(side, 0.0, 1.0)
        assert self.reach(side, np.array([p["x"], p["y"], top + 0.12]), yaw, 0.01)
        lifted = {o["name"]: o for o in self.read("/objects")["objects"]}[goal["object"]]
        assert lifted["pose"]["position"]["z"] > p["z"] + 0.1, "the object was not lifted"
        # Slide so that the area is 0.2 m to this arm's side, then lower the object into it.
        area = goal["target_center"]
        assert self.slide_to(area["y"] - (0.2 if side == "l" else -0.2))
        above_bottom = grasp - (p["z"] - target["size"]["z"] / 2)
        place = self.to_base(area["x"], area["y"], table + above_bottom + 0.12)
        assert self.reach(side, place, yaw, 0.01)
        place[2] = table + above_bottom + 0.005
        assert self.reach(side, place, yaw, 0.005)
        self.grip(side, 0.09, 0.5)
        place[2] += 0.12
        self.reach(side, place, yaw, 0.01)
        self.wait(lambda: False, 3.0)  # the episode ends when the object has settled


@pytest.fixture
def sim() -> Simulation:
    return Simulation(TASK, {}, seed=3)


def test_layout_is_drawn_from_the_seed_without_overlap_within_reach():
    """Objects stand apart, in the reachable region, off the target area; seeds differ."""
    layouts = set()
    for seed in range(20):
        plan = scene.layout(np.random.RandomState(seed), 6)
        things = plan.things
        assert len({t.name for t in things}) == 6 and plan.target in {t.name for t in things}
        for i, a in enumerate(things):
            assert scene.PLACE_X[0] <= a.x <= scene.PLACE_X[1]
            assert scene.PLACE_Y[0] <= a.y <= scene.PLACE_Y[1]
            gap = max(abs(a.x - plan.area[0]), abs(a.y - plan.area[1])) - scene.AREA_HALF
            assert gap >= a.radius
            for b in things[i + 1 :]:
                assert math.hypot(a.x - b.x, a.y - b.y) >= a.radius + b.radius + scene.CLEARANCE
        layouts.add(plan)
    assert len(layouts) == 20


def test_same_seed_same_model_and_another_seed_another():
    """The compiled model XML is a function of the seed and parameters."""
    first = Simulation(TASK, {}, seed=4).model_xml()
    assert first == Simulation(TASK, {}, seed=4).model_xml()
    assert first != Simulation(TASK, {}, seed=5).model_xml()


def test_parameters_are_validated():
    """Object counts and control rates outside what the task supports are refused."""
    params = registry.get(TASK).params
    assert params.validate({})["objects"] == 3
    with pytest.raises(ParamError, match="objects"):
        params.validate({"objects": 7})
    with pytest.raises(ParamError, match="control_rate"):
        params.validate({"control_rate": 30})


def test_base_velocity_moves_the_base_as_commanded(sim):
    """Sideways at 0.2 m/s for 2 s moves 0.4 m; turning at 0.5 rad/s for 2 s turns 1 rad."""
    sim.task.command("/base/cmd_vel", twist(y=0.2))
    seconds(sim, 2.0)
    sim.task.command("/base/cmd_vel", twist())
    seconds(sim, 0.5)
    position, _ = transform(sim, "base_footprint")
    assert position[1] == pytest.approx(0.4, abs=0.02)
    assert abs(position[0]) < 0.01
    sim.task.command("/base/cmd_vel", twist(turn=0.5))
    seconds(sim, 2.0)
    sim.task.command("/base/cmd_vel", twist())
    seconds(sim, 0.5)
    assert yaw_of(transform(sim, "base_footprint")[1]) == pytest.approx(1.0, abs=0.03)
    assert sim.task.clipped == {}


def test_joint_trajectory_reaches_its_targets_in_the_commanded_time(sim):
    """The right arm's joints are halfway at half the time and on target soon after it."""
    start = np.array(observe(sim, "/joint_states")["position"][10:17])
    goal = start + np.array([0.3, -0.6, 0.3, 0.3, 0.5, 0.4, -0.5])
    sim.task.command("/right_arm/command", trajectory(RIGHT_ARM, (goal.tolist(), 2.0)))
    seconds(sim, 1.0)
    halfway = np.array(observe(sim, "/joint_states")["position"][10:17])
    assert np.allclose(halfway, (start + goal) / 2, atol=0.06)
    seconds(sim, 1.3)
    state = observe(sim, "/joint_states")
    assert state["name"][10:17] == RIGHT_ARM
    assert np.allclose(state["position"][10:17], goal, atol=0.01)
    assert sim.task.clipped == {}


def test_out_of_range_targets_are_clipped_and_counted(sim):
    """A torso target above 0.31 m stops at 0.31 m; an opening of 0.2 m at 0.09 m; both count."""
    sim.task.command("/torso/command", trajectory(["torso_lift_joint"], ([0.5], 0.0)))
    sim.task.command("/left_gripper/command", {"data": 0.2})
    sim.task.command("/base/cmd_vel", twist(x=0.4, y=-0.4))  # 0.57 m/s: scaled to 0.5
    assert sim.task.clipped == {
        "/torso/command": 1,
        "/left_gripper/command": 1,
        "/base/cmd_vel": 1,
    }
    sim.task.command("/base/cmd_vel", twist())
    seconds(sim, 8.0)
    state = dict(
        zip(*(observe(sim, "/joint_states")[k] for k in ("name", "position")), strict=True)
    )
    assert state["torso_lift_joint"] == pytest.approx(0.31, abs=0.002)
    assert state["l_gripper_joint"] == pytest.approx(0.09, abs=0.002)
    assert sim.metrics()["clipped_commands"] == 3


def test_nan_and_infinity_are_refused_naming_the_field(sim):
    """A NaN or an infinity is refused with the field's path and changes nothing."""
    with pytest.raises(MessageError, match=r"points\[0\]\.positions\[1\]"):
        sim.task.command("/left_arm/command", trajectory(LEFT_ARM[:2], ([0.1, math.nan], 1.0)))
    with pytest.raises(MessageError, match=r"pose\.position\.z"):
        sim.task.command("/left_arm/pose", pose(np.array([0.5, 0.2, math.inf]), down(0.0)))
    with pytest.raises(MessageError, match=r"angular\.z"):
        sim.task.command("/base/cmd_vel", twist(turn=-math.inf))
    with pytest.raises(MessageError, match=r"joint_names\[0\]"):
        sim.task.command("/left_arm/command", trajectory(["r_elbow_flex_joint"], ([0.0], 1.0)))
    with pytest.raises(MessageError, match=r"header\.frame_id"):
        sim.task.command("/left_arm/pose", pose(np.zeros(3), down(0.0), frame="map"))
    with pytest.raises(MessageError, match=r"points\[1\]\.positions\[0\]"):
        sim.task.command(
            "/torso/command", trajectory(["torso_lift_joint"], ([9.0], 1), ([math.nan], 2))
        )
    assert sim.task.trajectories == {} and sim.task.poses == {} and sim.task.clipped == {}
    assert not np.any(sim.task.base_command)


def test_pose_command_brings_the_tool_frame_to_the_target():
    """After untucking, a pose command puts the left tool frame within 5 mm and 2 degrees."""
    sim = Simulation(TASK, {}, seed=3)
    controller = PickAndPlace(sim)
    controller.untuck()
    target = np.array([0.62, 0.12, 0.9])
    sim.task.command("/left_arm/pose", pose(target, down(0.4)))
    seconds(sim, 2.5)
    position, rotation = transform(sim, "l_gripper_tool_frame")
    assert np.linalg.norm(position - target) < 0.005
    wanted = down(0.4)
    dot = abs(sum(rotation[k] * wanted[k] for k in "xyzw"))
    assert 2 * math.degrees(math.acos(min(1.0, dot))) < 2.0


def test_objects_in_view_are_reported_and_hidden_ones_are_not(sim):
    """All objects are seen at the start; none with the head turned away; one under the
    table (in the image's frame but hidden by the table top) is not."""
    seen = observe(sim, "/objects")
    assert seen["header"]["frame_id"] == "base_footprint"
    names = [o["name"] for o in seen["objects"]]
    assert names == [t.name for t in sim.task.plan.things]
    first = seen["objects"][0]
    thing = sim.task.plan.things[0]
    assert first["pose"]["position"]["x"] == pytest.approx(thing.x, abs=0.002)
    assert first["size"]["z"] == pytest.approx(thing.size[2])
    # Hide the first object under the table top, where the camera looks.
    physics = sim.physics
    physics.named.data.qpos[thing.name][[0, 2]] = [0.85, 0.35]
    physics.forward()
    optical = sim.task.camera.to_optical(physics, physics.object_position(thing.name)[None])
    column, row = sim.task.camera.project(physics, optical)[0]
    assert 0 <= column < 320 and 0 <= row < 240 and optical[0, 2] > 0
    assert thing.name not in [o["name"] for o in observe(sim, "/objects")["objects"]]
    sim.task.command("/head/command", trajectory(["head_pan_joint"], ([math.pi / 2], 1.0)))
    seconds(sim, 1.5)
    assert observe(sim, "/objects")["objects"] == []


def test_head_camera_image_is_a_jpeg_of_the_configured_size(sim):
    """The image decodes as a 320 x 240 JPEG; camera_info agrees and names the frame."""
    image = observe(sim, "/camera/image/compressed")
    assert image["format"] == "jpeg"
    assert image["header"]["frame_id"] == "head_camera_optical_frame"
    decoded = Image.open(io.BytesIO(image["data"]))
    assert decoded.format == "JPEG" and decoded.size == (320, 240)
    info = observe(sim, "/camera/camera_info")
    assert (info["width"], info["height"]) == (320, 240)


def test_goal_names_an_object_and_an_area_on_the_table(sim):
    """The goal names one of the objects and the area the layout marked, in odom."""
    goal = observe(sim, "/task/goal")
    assert goal["header"]["frame_id"] == "odom"
    assert goal["object"] == sim.task.plan.target
    assert goal["target_center"]["x"] == sim.task.plan.area[0]
    assert goal["target_size"]["x"] == pytest.approx(2 * scene.AREA_HALF)


@pytest.mark.parametrize(("seed", "objects"), [(3, 3), (11, 6)])
def test_scripted_pick_and_place_succeeds(seed, objects):
    """A controller using only the documented topics moves the object and the task says so."""
    sim = Simulation(TASK, {"objects": objects}, seed=seed)
    PickAndPlace(sim).run()
    assert sim.status is EpisodeStatus.SUCCEEDED, sim.reason
    assert sim.reason.startswith(f"the {sim.task.plan.target} rests in the target area, 0.0")
    metrics = sim.metrics()
    assert metrics["success"] is True and metrics["dropped"] is False
    assert metrics["object_to_target"] < scene.AREA_HALF
    assert metrics["clipped_commands"] == 0


def test_an_object_off_the_table_fails_the_episode(sim):
    """The goal's object on the floor ends the episode as failed, naming it."""
    name = sim.task.plan.target
    sim.physics.named.data.qpos[name][:3] = [1.5, 0.0, 0.1]
    sim.physics.forward()
    sim.step()
    assert sim.status is EpisodeStatus.FAILED
    assert sim.reason == f"the {name} fell off the table"
    assert sim.metrics()["dropped"] is True


def test_a_diverging_physics_fails_the_episode_without_a_crash(sim):
    """Non-finite state ends the episode as failed with the physics' reason."""
    sim.task.command("/left_arm/pose", pose(np.array([0.5, 0.2, 0.9]), down(0.0)))
    sim.step()
    sim.physics.data.qvel[:] = math.inf
    sim.step()
    assert sim.status is EpisodeStatus.FAILED
    assert "diverged" in sim.reason
