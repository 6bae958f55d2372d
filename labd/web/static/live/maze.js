// The maze robot's page's arithmetic (icreate.js): its keys and stick as velocities, its
// odometry, the goal and the tags it saw in words and places. Plain values only, so that
// Node's test runner checks them (tests/js/pages/maze.test.mjs).

export const SPEED = 0.3, TURN = 1.6;  // m/s and rad/s at full stick
export const KEYS = {
  ArrowUp: [1, 0], w: [1, 0], ArrowDown: [-1, 0], s: [-1, 0],
  ArrowLeft: [0, 1], a: [0, 1], ArrowRight: [0, -1], d: [0, -1],
};
const CAMERA_IN_BASE = 0.12;  // m ahead of base_link (docs/tasks.md)
const DEAD = 0.15;  // of a stick's travel, taken as none
const PATH_STEP = 0.02;  // m between the points of the path drawn

/** A geometry_msgs/msg/Twist of ``v`` m/s ahead and ``w`` rad/s to the left. */
export const twist = (v, w) => ({ linear: { x: v, y: 0, z: 0 }, angular: { x: 0, y: 0, z: w } });

/** A quaternion's rotation about z. */
export const yaw = (q) => Math.atan2(2 * (q.w * q.z + q.x * q.y), 1 - 2 * (q.y * q.y + q.z * q.z));

/** A key as KEYS names it (letters in lower case, whatever the shift). */
export const keyName = (key) => (key.length === 1 ? key.toLowerCase() : key);

/** The velocity the ``held`` keys ask for (full speed and turn, by their signs), or null. */
export function keysTwist(held) {
  let v = 0, w = 0;
  for (const k of held) { v += KEYS[k][0]; w += KEYS[k][1]; }
  return held.size ? twist(SPEED * Math.sign(v), TURN * Math.sign(w)) : null;
}

/** The velocity of a pad's or stick's ``v`` and ``w`` (-1 to 1), or null for none. */
export const padTwist = (v, w) => (v || w ? twist(SPEED * v, TURN * w) : null);

/** A gamepad's [v, w]: the left stick (up is ahead, left turns left) past its dead zone,
 * or the d-pad (buttons 12 to 15) at full. */
export function stick(pad) {
  const dead = (x) => (Math.abs(x) < DEAD ? 0 : x);
  let v = -dead(pad.axes[1] || 0), w = -dead(pad.axes[0] || 0);
  if (pad.buttons[12]?.pressed) v = 1;
  if (pad.buttons[13]?.pressed) v = -1;
  if (pad.buttons[14]?.pressed) w = 1;
  if (pad.buttons[15]?.pressed) w = -1;
  return [v, w];
}

/** The robot's pose in odom ({x, y, th}) from a nav_msgs/msg/Odometry. */
export function odomPose(m) {
  const p = m.pose.pose.position;
  return { x: p.x, y: p.y, th: yaw(m.pose.pose.orientation) };
}

/** An odometry message in words: where, heading, and how fast. */
export function odomWords(m) {
  const { x, y, th } = odomPose(m);
  return `x ${x.toFixed(2)} m, y ${y.toFixed(2)} m, heading ${(th * 180 / Math.PI).toFixed(0)}°`
    + ` · ${m.twist.twist.linear.x.toFixed(2)} m/s, ${m.twist.twist.angular.z.toFixed(2)} rad/s`;
}

/** Add the point (x, y) to ``path`` once the robot moved 2 cm from its last one. */
export function extendPath(path, x, y) {
  const last = path[path.length - 1];
  if (!last || Math.hypot(last[0] - x, last[1] - y) > PATH_STEP) path.push([x, y]);
  return path;
}

/** The goal from the robot's ``pose``: how far, and how far to turn to which side. */
export function goalWords(goal, pose) {
  const dx = goal.x - pose.x, dy = goal.y - pose.y;
  let bearing = Math.atan2(dy, dx) - pose.th;
  bearing = Math.atan2(Math.sin(bearing), Math.cos(bearing));
  return `${Math.hypot(dx, dy).toFixed(2)} m away (straight line), `
    + `${Math.abs(bearing * 180 / Math.PI).toFixed(0)}° to the ${bearing >= 0 ? "left" : "right"}`;
}

/** A tag's centre in odom, from its position ``p`` in the camera's optical frame. */
export function inOdom(pose, p) {
  const ahead = CAMERA_IN_BASE + p.z, left = -p.x;
  const c = Math.cos(pose.th), s = Math.sin(pose.th);
  return [pose.x + c * ahead - s * left, pose.y + s * ahead + c * left];
}
