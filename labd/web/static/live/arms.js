// The PR2 page's commands (pr2.js), as messages: the base's velocity from the keys held,
// joint trajectories (torso, head, arms), the arms' ready pose and a Cartesian target.
// Plain values only, so that Node's test runner checks them (tests/js/pages/pr2.test.mjs).

export const STEP = 0.02;  // m per key press of a target
export const TARGET_KEYS = { i: [1, 0, 0], k: [-1, 0, 0], j: [0, 1, 0], l: [0, -1, 0], u: [0, 0, 1], o: [0, 0, -1] };
export const BASE_KEYS = { w: [1, 0, 0], s: [-1, 0, 0], a: [0, 1, 0], d: [0, -1, 0], q: [0, 0, 1], e: [0, 0, -1] };
const BASE_SPEED = 0.2, BASE_TURN = 0.5;  // m/s and rad/s of a key held
export const READY = {  // the arms' ready pose and the joints' names (docs/tasks.md)
  left: [0.66, -0.18, 1.34, -1.65, 1.37, -1.78, 2.1],
  right: [-0.66, -0.18, -1.34, -1.65, -1.37, -1.78, 1.04],
};
const JOINTS = ["shoulder_pan", "shoulder_lift", "upper_arm_roll", "elbow_flex", "forearm_roll", "wrist_flex", "wrist_roll"];
const LIFT = -0.5;  // the shoulder's lift while an arm moves over the table

export const ZERO_TWIST = { linear: { x: 0, y: 0, z: 0 }, angular: { x: 0, y: 0, z: 0 } };

/** The base's velocity for the ``held`` keys of BASE_KEYS (ahead, left, turn), or null. */
export function baseTwist(held) {
  const v = [0, 0, 0];
  for (const k of held) BASE_KEYS[k].forEach((x, i) => { v[i] += x; });
  return held.size
    ? { linear: { x: BASE_SPEED * v[0], y: BASE_SPEED * v[1], z: 0 }, angular: { x: 0, y: 0, z: BASE_TURN * v[2] } }
    : null;
}

/** A trajectory_msgs/msg/JointTrajectory through ``points``: [positions, seconds] each. */
export function trajectory(names, points) {
  return {
    header: { stamp: { sec: 0, nanosec: 0 }, frame_id: "" }, joint_names: names,
    points: points.map(([positions, seconds]) => ({
      positions, velocities: [], accelerations: [], effort: [],
      time_from_start: { sec: Math.floor(seconds), nanosec: Math.round((seconds % 1) * 1e9) },
    })),
  };
}

/** The joints of the ``side`` arm ("left", "right"), shoulder to wrist. */
export const armJoints = (side) => JOINTS.map((j) => `${side[0]}_${j}_joint`);

/** From the arm's joints ``now`` to ``ready`` without sweeping the table: lift the
 * shoulder, swing, then lower it ([positions, seconds] each). */
export function readyPlan(now, ready) {
  const lifted = (pose) => pose.map((x, i) => (i === 1 ? LIFT : x));
  return [[lifted(now), 2], [lifted(ready), 4], [ready, 5]];
}

/** A geometry_msgs/msg/PoseStamped of a target: position ``p`` and orientation ``o``
 * (x, y, z and w) in base_footprint. */
export function targetPose(p, o) {
  return {
    header: { stamp: { sec: 0, nanosec: 0 }, frame_id: "base_footprint" },
    pose: { position: { x: p.x, y: p.y, z: p.z }, orientation: { x: o.x, y: o.y, z: o.z, w: o.w } },
  };
}

/** Where a target is, in words and as a ux event's value (m, to the mm). */
export const targetWords = (p) => `(${p.x.toFixed(2)}, ${p.y.toFixed(2)}, ${p.z.toFixed(2)}) m`;
export const targetEvent = (p) => ({ x: +p.x.toFixed(3), y: +p.y.toFixed(3), z: +p.z.toFixed(3) });
