"""Pick up the pr2-table task's object and put it down in the target area, with roslibpy.

A plain roslibpy program, as any ROS user would write one: it reads the bridge's URL
from LAB_BRIDGE_URL and uses the task's documented topics only (docs/tasks.md, "A
pick and place, step by step"):

1. Read /task/goal. Untuck: torso up, then each arm over the table to the ready pose.
2. Find the object on /objects (in base_footprint); pick the arm on its side; for a
   box, turn the gripper by the box's yaw modulo 90 degrees.
3. Open the gripper; bring the tool frame (a pose command, pointing down) 8 cm above
   the object, then down around it, watching /tf.
4. Close the gripper, wait a second, lift.
5. Slide the base sideways until the target area is 0.2 m to the arm's side.
6. Bring the object over the area, lower it to 5 mm above the table, open, lift away,
   and step until the lab declares the episode over.

Time moves only when the controller calls /lab/step (lockstep): the lab applies the
commands published before the call, advances one tick, publishes that tick's
observations, and then answers. roslibpy runs its callbacks on its reactor thread in
the order the frames arrived, so by the time the blocking service call returns, the
callbacks for that tick's observations have run; ``Robot.step`` still checks it, and
waits on a condition for the tick's /tf if it were not so.
"""

from __future__ import annotations

import logging
import math
import os
import re
import sys
import threading
from collections.abc import Callable, Sequence
from typing import Any
from urllib.parse import urlsplit

import roslibpy

WAIT = 30.0  # s of wall clock to wait for the lab before giving up
LEFT_ARM = [
    f"l_{joint}_joint"
    for joint in (
        "shoulder_pan",
        "shoulder_lift",
        "upper_arm_roll",
        "elbow_flex",
        "forearm_roll",
        "wrist_flex",
        "wrist_roll",
    )
]
ARMS = {"l": LEFT_ARM, "r": [name.replace("l_", "r_", 1) for name in LEFT_ARM]}
SIDES = {"l": "left", "r": "right"}
# Arms over the table, grippers pointing down (the ready pose of docs/tasks.md).
READY = {
    "l": [0.66, -0.18, 1.34, -1.65, 1.37, -1.78, 2.1],
    "r": [-0.66, -0.18, -1.34, -1.65, -1.37, -1.78, 1.04],
}
TOPICS = {  # observations
    "/task/goal": "lab_msgs/msg/TableGoal",
    "/objects": "lab_msgs/msg/DetectedObjectArray",
    "/tf": "tf2_msgs/msg/TFMessage",
    "/joint_states": "sensor_msgs/msg/JointState",
}
COMMANDS = {
    "/torso/command": "trajectory_msgs/msg/JointTrajectory",
    "/left_arm/command": "trajectory_msgs/msg/JointTrajectory",
    "/right_arm/command": "trajectory_msgs/msg/JointTrajectory",
    "/left_arm/pose": "geometry_msgs/msg/PoseStamped",
    "/right_arm/pose": "geometry_msgs/msg/PoseStamped",
    "/left_gripper/command": "std_msgs/msg/Float64",
    "/right_gripper/command": "std_msgs/msg/Float64",
    "/base/cmd_vel": "geometry_msgs/msg/Twist",
}
# "tick 12 at 0.600 s: running", "tick 500 at 25.000 s: succeeded: the red_box rests ..."
ANSWER = re.compile(r"tick (\d+) at ([0-9.]+) s: (\w+)(?:: (.*))?", re.DOTALL)
ZERO = {"sec": 0, "nanosec": 0}

log = logging.getLogger("pick-place")
Vector = list[float]


class EpisodeEnded(Exception):
    """The lab said the episode is over: ``message`` is its sentence."""


class Robot:
    """The lab's robot over roslibpy: the latest observations, commands, and steps."""

    def __init__(self, ros: roslibpy.Ros) -> None:
        self.ros = ros
        self.latest: dict[str, dict[str, Any]] = {}
        self.arrived = threading.Condition()  # notified from roslibpy's reactor thread
        self.time = 0.0  # simulation seconds, from the answers to /lab/step
        self.listeners: list[roslibpy.Topic] = []
        for topic, type_name in TOPICS.items():
            listener = roslibpy.Topic(ros, topic, type_name)
            listener.subscribe(self._keeper(topic))
            self.listeners.append(listener)
        self.publishers = {
            topic: roslibpy.Topic(ros, topic, type_name) for topic, type_name in COMMANDS.items()
        }
        self.stepper = roslibpy.Service(ros, "/lab/step", "std_srvs/srv/Trigger")
        with self.arrived:  # latched: each topic's current message comes on subscribing
            if not self.arrived.wait_for(lambda: len(self.latest) == len(TOPICS), WAIT):
                raise TimeoutError(f"no first message on {set(TOPICS) - set(self.latest)}")

    def _keeper(self, topic: str) -> Callable[[dict[str, Any]], None]:
        def keep(message: dict[str, Any]) -> None:
            with self.arrived:
                self.latest[topic] = message
                self.arrived.notify_all()

        return keep

    def read(self, topic: str) -> dict[str, Any]:
        with self.arrived:
            return self.latest[topic]

    def send(self, topic: str, message: dict[str, Any]) -> None:
        self.publishers[topic].publish(roslibpy.Message(message))

    def step(self) -> None:
        """Advance one tick; its observations are in ``latest`` when this returns.

        Raises EpisodeEnded when the lab says the episode is over.
        """
        answer = self.stepper.call(roslibpy.ServiceRequest(), timeout=WAIT)
        match = ANSWER.fullmatch(answer["message"])
        if not answer["success"] or not match:
            raise EpisodeEnded(answer["message"])
        self.time = float(match[2])
        # roslibpy has already run this tick's callbacks (frames are handled in order on
        # its reactor thread, the answer last); should that change, wait for them here.
        with self.arrived:
            if not self.arrived.wait_for(lambda: self._stamp("/tf") >= self.time - 1e-6, WAIT):
                raise TimeoutError(f"no /tf for the tick at {self.time:.3f} s")
        if match[3] != "running":
            raise EpisodeEnded(answer["message"])

    def _stamp(self, topic: str) -> float:
        stamp = self.latest[topic]["transforms"][0]["header"]["stamp"]
        return float(stamp["sec"] + stamp["nanosec"] / 1e9)

    def wait(self, done: Callable[[], bool], duration: float) -> bool:
        """Step until ``done()`` holds or ``duration`` simulated seconds pass; whether it held."""
        until = self.time + duration - 1e-6
        while not done() and self.time < until:
            self.step()
        return done()

    def transform(self, child: str) -> tuple[Vector, dict[str, float]]:
        """The translation and rotation of ``child`` in its parent frame, from /tf."""
        for item in self.read("/tf")["transforms"]:
            if item["child_frame_id"] == child:
                t = item["transform"]["translation"]
                return [t["x"], t["y"], t["z"]], item["transform"]["rotation"]
        raise KeyError(child)


def trajectory(names: list[str], *points: tuple[Sequence[float], float]) -> dict[str, Any]:
    """A JointTrajectory through ``points``: (positions, seconds from its start)."""
    return {
        "header": {"stamp": ZERO, "frame_id": ""},
        "joint_names": names,
        "points": [
            {
                "positions": list(positions),
                "time_from_start": {"sec": int(at), "nanosec": round(at % 1 * 1e9)},
            }
            for positions, at in points
        ],
    }


def twist(x: float = 0.0, y: float = 0.0, turn: float = 0.0) -> dict[str, Any]:
    return {"linear": {"x": x, "y": y, "z": 0.0}, "angular": {"x": 0.0, "y": 0.0, "z": turn}}


def down(yaw: float) -> dict[str, float]:
    """A tool frame pointing straight down (x along -z), turned ``yaw`` about z."""
    c, s, h = math.cos(yaw / 2), math.sin(yaw / 2), math.sqrt(0.5)
    return {"x": -s * h, "y": c * h, "z": s * h, "w": c * h}  # Rz(yaw) * Ry(90 degrees)


def pose(position: Vector, orientation: dict[str, float]) -> dict[str, Any]:
    x, y, z = position
    return {
        "header": {"stamp": ZERO, "frame_id": "base_footprint"},
        "pose": {"position": {"x": x, "y": y, "z": z}, "orientation": orientation},
    }


def yaw_of(q: dict[str, float]) -> float:
    return math.atan2(2 * (q["w"] * q["z"] + q["x"] * q["y"]), 1 - 2 * (q["y"] ** 2 + q["z"] ** 2))


def distance(a: Vector, b: Vector) -> float:
    return math.dist(a, b)


class PickAndPlace:
    """The recipe of docs/tasks.md, over the robot's topics."""

    def __init__(self, robot: Robot) -> None:
        self.robot = robot

    def untuck(self) -> None:
        """Torso up first, then each arm: upper arm raised, turned, lowered to READY,
        so that nothing sweeps across the table."""
        robot = self.robot
        robot.send("/torso/command", trajectory(["torso_lift_joint"], ([0.2], 4.0)))
        robot.wait(lambda: False, 4.0)
        state = robot.read("/joint_states")
        now = dict(zip(state["name"], state["position"], strict=True))
        for side, names in ARMS.items():
            raised = [now[n] for n in names]
            raised[1] = -0.5  # shoulder_lift: upper arm up
            turned = list(READY[side])
            turned[1] = -0.5
            command = trajectory(names, (raised, 2.0), (turned, 4.0), (READY[side], 5.0))
            robot.send(f"/{SIDES[side]}_arm/command", command)
        robot.wait(lambda: False, 5.5)

    def reach(self, side: str, target: Vector, yaw: float, tolerance: float) -> bool:
        """Tool frame to ``target`` (base_footprint), pointing down; whether it got there."""
        self.robot.send(f"/{SIDES[side]}_arm/pose", pose(target, down(yaw)))
        tool = f"{side}_gripper_tool_frame"
        return self.robot.wait(
            lambda: distance(self.robot.transform(tool)[0], target) < tolerance, 5.0
        )

    def grip(self, side: str, opening: float, duration: float) -> None:
        self.robot.send(f"/{SIDES[side]}_gripper/command", {"data": opening})
        self.robot.wait(lambda: False, duration)

    def slide_to(self, y: float) -> bool:
        """Drive the base sideways until base_footprint is at odom ``y``."""

        def there() -> bool:
            error = y - self.robot.transform("base_footprint")[0][1]
            self.robot.send("/base/cmd_vel", twist(y=max(-0.3, min(0.3, 2.0 * error))))
            return abs(error) < 0.003

        arrived = self.robot.wait(there, 10.0)
        self.robot.send("/base/cmd_vel", twist())
        return arrived

    def to_base(self, x: float, y: float, z: float) -> Vector:
        """An odom point in base_footprint (the base only moves in the plane)."""
        (bx, by, _), rotation = self.robot.transform("base_footprint")
        yaw = yaw_of(rotation)
        dx, dy = x - bx, y - by
        c, s = math.cos(yaw), math.sin(yaw)
        return [c * dx + s * dy, -s * dx + c * dy, z]

    def check(self, done: bool, what: str) -> None:
        if not done:
            log.warning("%.2f s: %s: not within tolerance, carrying on", self.robot.time, what)

    def run(self) -> None:
        robot = self.robot
        goal = robot.read("/task/goal")
        table = goal["table_center"]["z"]
        log.info("move the %s to %s", goal["object"], goal["target_center"])
        # Where the object is: seen now, with the arms tucked, and again once they are
        # over the table (which may hide it; it has not moved if so).
        seen = {o["name"]: o for o in robot.read("/objects")["objects"]}
        self.untuck()
        seen.update({o["name"]: o for o in robot.read("/objects")["objects"]})
        target = seen[goal["object"]]
        p, q = target["pose"]["position"], target["pose"]["orientation"]
        side = "l" if p["y"] >= 0 else "r"
        # Close across a box's faces: its yaw modulo 90 degrees, the smallest turn.
        yaw = yaw_of(q) if target["shape"] == "box" else 0.0
        yaw = (yaw + math.pi / 4) % (math.pi / 2) - math.pi / 4
        top = p["z"] + target["size"]["z"] / 2
        grasp = max(top - 0.03, table + 0.025)  # fingertips reach 0.02 m past the tool frame
        log.info("%.2f s: %s arm to the %s at %s", robot.time, SIDES[side], target["shape"], p)
        self.grip(side, 0.09, 0.2)
        self.check(self.reach(side, [p["x"], p["y"], top + 0.08], yaw, 0.01), "above the object")
        self.check(self.reach(side, [p["x"], p["y"], grasp], yaw, 0.005), "around the object")
        self.grip(side, 0.0, 1.0)
        self.check(self.reach(side, [p["x"], p["y"], top + 0.12], yaw, 0.01), "lifted")
        lifted = {o["name"]: o for o in robot.read("/objects")["objects"]}.get(goal["object"])
        if lifted is None or lifted["pose"]["position"]["z"] < p["z"] + 0.1:
            log.warning("%.2f s: the %s does not seem lifted", robot.time, goal["object"])
        # Slide so that the area is 0.2 m to this arm's side, then lower the object into it.
        area = goal["target_center"]
        self.check(self.slide_to(area["y"] - (0.2 if side == "l" else -0.2)), "base slid")
        above_bottom = grasp - (p["z"] - target["size"]["z"] / 2)
        place = self.to_base(area["x"], area["y"], table + above_bottom + 0.12)
        log.info("%.2f s: carrying it over the area", robot.time)
        self.check(self.reach(side, place, yaw, 0.01), "over the area")
        place[2] = table + above_bottom + 0.005
        self.check(self.reach(side, place, yaw, 0.005), "down on the table")
        self.grip(side, 0.09, 0.5)
        place[2] += 0.12
        self.reach(side, place, yaw, 0.01)
        log.info("%.2f s: placed; waiting for the lab to see it rest", robot.time)
        while True:  # until the lab ends the episode (success, or the time limit)
            robot.step()


def connect(url: str) -> roslibpy.Ros:
    """A roslibpy client for ``url`` (ws://HOST:PORT, or a full URL with a path)."""
    parts = urlsplit(url)
    if parts.path in ("", "/"):
        ros = roslibpy.Ros(host=parts.hostname, port=parts.port, is_secure=parts.scheme == "wss")
    else:
        ros = roslibpy.Ros(host=url)  # roslibpy takes a whole URL when given no port
    ros.run(timeout=WAIT)
    return ros


def main() -> int:
    logging.basicConfig(format="%(name)s: %(message)s", stream=sys.stdout)
    log.setLevel(logging.INFO)
    ros = connect(os.environ.get("LAB_BRIDGE_URL", "ws://127.0.0.1:9090"))
    try:
        PickAndPlace(Robot(ros)).run()
    except EpisodeEnded as ended:
        log.info("episode over: %s", ended)
    finally:
        closed = threading.Event()
        ros.on("close", lambda _: closed.set())
        ros.close()
        closed.wait(WAIT)  # the closing handshake, before the reactor stops
        ros.terminate()
    return 0


if __name__ == "__main__":
    sys.exit(main())
