"""How commands become joint setpoints: trajectory following and Cartesian (IK) control.

The robot's position servos track a vector of setpoints, one per commanded joint.
Each control tick the task moves every setpoint toward a reference, no faster than
the joint's speed limit:

- a ``JointTrajectory`` gives the reference by linear interpolation in simulation
  time, from the setpoints when it started, through its points;
- a pose target gives it by damped-least-squares inverse kinematics on MuJoCo's
  Jacobians, computed on a scratch copy of the state at the *setpoints* (not the
  measured joints), so that contact or load never winds it up. The tool frame is led
  toward the target along a straight line at a bounded speed, so that a grasp
  approaches the way it was asked to.

Everything here is plain arithmetic on the state: the same state and commands give
the same setpoints, bit for bit.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from labd.sim.pr2 import model

LINEAR_SPEED = 0.3  # m/s: how fast a pose command moves the tool frame
ANGULAR_SPEED = 1.5  # rad/s: how fast it turns it
ROTATION_WEIGHT = 0.5  # m per rad: orientation error against position error
DAMPING = 0.05  # damped least squares: bounds the step near singularities
ITERATIONS = 3  # Gauss-Newton steps per tick toward the tick's waypoint
POSTURE_GAIN = 0.05  # per step: how strongly the redundant elbow swivel leans to READY


@dataclass
class Trajectory:
    """A joint trajectory being followed.

    ``indices`` select its joints in the setpoint vector; ``times`` (s, from its
    start, non-decreasing) and ``points`` (one row per time) are the message's.
    ``start`` and ``started`` are filled in on the first tick it is followed.
    """

    indices: np.ndarray
    times: np.ndarray
    points: np.ndarray
    started: float | None = None
    start: np.ndarray | None = None

    def reference(self, now: float, setpoints: np.ndarray) -> np.ndarray:
        """Where its joints should be at simulation time ``now``."""
        if self.started is None or self.start is None:
            self.started = now
            self.start = setpoints[self.indices].copy()
        elapsed = now - self.started
        times = self.times
        k = int(np.searchsorted(times, elapsed, side="right"))
        if k >= len(times):
            last: np.ndarray = self.points[-1]
            return last
        t0 = times[k - 1] if k > 0 else 0.0
        p0 = self.points[k - 1] if k > 0 else self.start
        a = (elapsed - t0) / (times[k] - t0)  # times[k] > elapsed >= t0
        out: np.ndarray = p0 + a * (self.points[k] - p0)
        return out


@dataclass
class PoseTarget:
    """A tool frame pose to reach: position and rotation matrix in ``frame``."""

    frame: str
    position: np.ndarray
    rotation: np.ndarray  # 3 x 3


class ArmSolver:
    """Damped-least-squares IK for one arm's tool frame, on a scratch MjData."""

    def __init__(self, mj_model: mujoco.MjModel, side: str) -> None:
        self.model = mj_model
        self.data = mujoco.MjData(mj_model)
        joints = model.ARMS[side]
        ids = [mj_model.joint(j.name).id for j in joints]
        self.qpos = np.array([mj_model.jnt_qposadr[i] for i in ids])
        self.dofs = np.array([mj_model.jnt_dofadr[i] for i in ids])
        self.low = np.array([j.low for j in joints])
        self.high = np.array([j.high for j in joints])
        self.site = mj_model.site(f"{side}_gripper_tool_frame").id
        self.ready = np.array(model.READY[side])
        self._jacp = np.zeros((3, mj_model.nv))
        self._jacr = np.zeros((3, mj_model.nv))
        self._quat = np.zeros(4)
        self._error_quat = np.zeros(4)
        self._inverse = np.zeros(4)
        self._velocity = np.zeros(3)

    def _forward(self, qpos: np.ndarray, arm: np.ndarray) -> None:
        self.data.qpos[:] = qpos
        self.data.qpos[self.qpos] = arm
        mujoco.mj_kinematics(self.model, self.data)
        mujoco.mj_comPos(self.model, self.data)

    def _rotation_error(self, goal: np.ndarray) -> np.ndarray:
        """The rotation (axis times angle, world frame) from the tool's to ``goal``."""
        mujoco.mju_mat2Quat(self._quat, self.data.site_xmat[self.site])
        mujoco.mju_negQuat(self._inverse, self._quat)
        mujoco.mju_mulQuat(self._error_quat, goal, self._inverse)
        mujoco.mju_quat2Vel(self._velocity, self._error_quat, 1.0)
        return self._velocity.copy()

    def tool(self, qpos: np.ndarray, arm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The tool frame's world position and rotation matrix with the arm at ``arm``."""
        self._forward(qpos, arm)
        return (
            self.data.site_xpos[self.site].copy(),
            self.data.site_xmat[self.site].reshape(3, 3).copy(),
        )

    def step(
        self,
        qpos: np.ndarray,
        arm: np.ndarray,
        position: np.ndarray,
        rotation: np.ndarray,
        *,
        dt: float,
        speed: np.ndarray,
    ) -> np.ndarray:
        """The arm's next setpoints (from ``arm``), a tick of ``dt`` toward the target.

        ``qpos`` is the current state (for the base, torso and the other arm);
        ``position`` and ``rotation`` the target in the world frame; ``speed`` the
        joints' speed limits. An unreachable target is approached as near as the
        arm allows: the least-squares step settles where the error stops shrinking.
        """
        self._forward(qpos, arm)
        here = self.data.site_xpos[self.site].copy()
        goal_quat = np.zeros(4)
        mujoco.mju_mat2Quat(goal_quat, rotation.reshape(9))
        # This tick's waypoint: a bounded move along the straight line to the target.
        offset = position - here
        distance = float(np.linalg.norm(offset))
        if distance > LINEAR_SPEED * dt:
            offset *= LINEAR_SPEED * dt / distance
        waypoint = here + offset
        turn = self._rotation_error(goal_quat)
        angle = float(np.linalg.norm(turn))
        if angle > ANGULAR_SPEED * dt:
            turn *= ANGULAR_SPEED * dt / angle
            partial = np.zeros(4)
            mujoco.mju_axisAngle2Quat(partial, turn / np.linalg.norm(turn), ANGULAR_SPEED * dt)
            mujoco.mju_mulQuat(goal_quat, partial, self._quat.copy())
        q = arm.copy()
        error = np.zeros(6)
        jacobian = np.zeros((6, len(q)))
        for i in range(ITERATIONS):
            if i:
                self._forward(qpos, q)
            error[:3] = waypoint - self.data.site_xpos[self.site]
            error[3:] = ROTATION_WEIGHT * self._rotation_error(goal_quat)
            mujoco.mj_jacSite(self.model, self.data, self._jacp, self._jacr, self.site)
            jacobian[:3] = self._jacp[:, self.dofs]
            jacobian[3:] = ROTATION_WEIGHT * self._jacr[:, self.dofs]
            gram = jacobian @ jacobian.T + DAMPING**2 * np.eye(6)
            inverse = jacobian.T @ np.linalg.inv(gram)
            # The pose error first; in what it leaves free, lean toward READY.
            posture = (np.eye(len(q)) - inverse @ jacobian) @ (POSTURE_GAIN * (self.ready - q))
            q = np.clip(q + inverse @ error + posture, self.low, self.high)
        limit = speed * dt
        out: np.ndarray = arm + np.clip(q - arm, -limit, limit)
        return out
