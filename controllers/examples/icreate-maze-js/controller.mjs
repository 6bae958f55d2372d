// Solve the icreate-maze task: reach the goal cell of an unknown maze.
//
// A JavaScript (Node.js 20, ESM) port of controllers/examples/icreate-maze/controller.py,
// talking to the lab with roslibjs (npm `roslib` 2.x): the same algorithm, the same
// constants, the same decisions.
//
// The maze is a grid of 0.75 m cells, each floor or a solid block of wall, axis-aligned
// in the odometry frame with the start cell's centre at the origin (docs/tasks.md), so
// the controller keeps a map of cells (unknown, floor, wall) and plans on it:
//
// - Plan the quickest way to the goal cell (from /goal) with Dijkstra over cells and
//   headings: unknown cells count as floor (a little dearer than known floor), turns
//   cost time too. Re-plan whenever the robot enters a cell or learns something.
// - Move from cell centre to cell centre: turn in place toward the next cell, then drive
//   along the grid line, steering back onto it, through straight runs without stopping;
//   slow down before entering a cell not known to be floor.
// - Map with the bumpers: a bump while driving into a cell means it is wall (the robot
//   backs up to the cell it came from and re-plans); a cell the robot's front has
//   entered without a bump is floor. And with the tags: a tag hangs on a wall face, so
//   the cell behind it is wall, the one in front floor, and the camera's line of sight
//   to it crosses only floor.
// - Stay localised. Wheel odometry drifts a little. The tag detector is exact and tags
//   hang at known places on the grid (centred on a cell's face, 0.2 m up), so every tag
//   seen fixes the heading (its face is along a grid axis) and the position (its centre
//   is on the grid's lattice of faces). A head-on bump fixes the position along the
//   direction of travel (the wall's face is on a cell boundary).
//
// Lockstep: each control tick it publishes /cmd_vel and then calls /lab/step
// (std_srvs/srv/Trigger); the lab steps, publishes the tick's observations and only then
// answers, so when the answer arrives the newest message of each subscription is this
// tick's. It uses only /odom, /bumper, /ar_tags, /goal, /lab/episode, /cmd_vel and
// /lab/step. Everything depends on the messages only (no randomness, no wall clock in any
// decision), so the same seed gives the same run. Python's rounding (half to even) and
// modulo (the sign of the divisor) are reproduced where the Python controller uses them.

import { existsSync } from "node:fs";
import { Ros, Service, Topic } from "roslib";

const CELL = 0.75; // m: the maze's cells
const HALF = CELL / 2;
const RADIUS = 0.17; // m: the robot's disc
const CAMERA = 0.12; // m: the camera ahead of base_link (at the tags' height)

const MAX_SPEED = 0.5; // m/s
const PROBE_SPEED = 0.2; // m/s when the front reaches a cell not known to be floor
const TURN_SPEED = 3.0; // rad/s
const BRAKE = 0.8; // m/s^2 planned deceleration (the wheels manage 2.9)
const HEADING_GAIN = 5.0; // rad/s per rad of heading error
const TRACK_GAIN = 2.0; // rad of heading per m off the grid line
const ARRIVED = 0.03; // m from a cell's centre: close enough to turn there
const ALIGNED = 0.06; // rad: close enough to the heading to drive
const GIVE_UP = 10.0; // s a move may take (per cell): stuck, it re-plans from where it is

const UNKNOWN_COST = 0.4; // extra cost (in cells) of planning through an unknown cell
const TURN_COST = 0.6; // cost (in cells) of a quarter turn

const UNKNOWN = 0;
const FLOOR = 1;
const WALL = 2;
// The four headings: +x, +y, -x, -y in the grid (odom) frame.
const STEPS = [
  [1, 0],
  [0, 1],
  [-1, 0],
  [0, -1],
];

const DEFAULT_URL = "ws://127.0.0.1:9090";
const CONNECT_TIMEOUT = 10; // s (wall clock): a guard, never a decision
const STEP_TIMEOUT = 30; // s the lab may take to answer /lab/step
// The lab's /lab/step answers: "tick 12 at 1.200 s: running",
// "tick 600 at 60.000 s: truncated: the time limit of 60 s was reached".
const STEP_ANSWER = /^tick (\d+) at ([0-9.]+) s: (\w+)(?:: ([\s\S]*))?$/;
// "the episode has ended (truncated: the time limit ...)"
const ENDED_ANSWER = /^[\s\S]*\((\w+): ([\s\S]*)\)$/;

// -- logging (stderr, like the Python example's "maze: ..." lines) -----------------------

const log = {
  info: (text) => console.error(`maze: ${text}`),
  warning: (text) => console.error(`maze: ${text}`),
};

const seconds = (t) => t.toFixed(1);
const show = (cell) => `(${cell[0]}, ${cell[1]})`;

// -- Python's arithmetic ----------------------------------------------------------------

/** Python's round(x): the nearest integer, ties to even. */
function pyRound(x) {
  const r = Math.round(x);
  return Math.abs(x % 1) === 0.5 ? 2 * Math.round(x / 2) : r;
}

/** Python's a % b on floats (and ints): the result has the sign of the divisor. */
function pyMod(a, b) {
  let mod = a % b; // fmod
  if (mod !== 0) {
    if (b < 0 !== mod < 0) mod += b;
  } else {
    mod = b < 0 ? -0 : 0;
  }
  return mod;
}

/** Python's math.copysign. */
function copysign(x, sign) {
  return sign < 0 || Object.is(sign, -0) ? -Math.abs(x) : Math.abs(x);
}

/** `angle` in [-pi, pi). */
function wrap(angle) {
  return pyMod(angle + Math.PI, 2 * Math.PI) - Math.PI;
}

/** The yaw of a quaternion (rotation about z). */
function yawOf(q) {
  return Math.atan2(2 * (q.w * q.z + q.x * q.y), 1 - 2 * (q.y * q.y + q.z * q.z));
}

function cellOf(x, y) {
  return [pyRound(x / CELL), pyRound(y / CELL)];
}

const key = (cell) => `${cell[0]},${cell[1]}`;

// -- the lab, through roslibjs ----------------------------------------------------------

class LabError extends Error {}

/** The episode has ended: `tick` is its last tick (its observations are in the subscriptions). */
class EpisodeOver extends LabError {
  constructor(tick) {
    super(`the episode is over: ${tick.message}`);
    this.tick = tick;
  }
}

/** Where the episode is after a step: what /lab/step answered. */
class Tick {
  constructor(number, time, status, reason, message) {
    Object.assign(this, { number, time, status, reason, message });
  }

  get running() {
    return this.status === "running";
  }

  /** The tick a lab_msgs/msg/Episode message describes. */
  static fromEpisode(episode, message = "") {
    const stamp = episode.header.stamp;
    const time = stamp.sec + stamp.nanosec / 1e9;
    const status = String(episode.status);
    const reason = String(episode.reason);
    const text =
      message ||
      `tick ${episode.tick} at ${time.toFixed(3)} s: ${status}` + (reason ? `: ${reason}` : "");
    return new Tick(Number(episode.tick), time, status, reason, text);
  }
}

/** One topic's messages as they arrive: `latest` (null before the first) and `count`. */
class Subscription {
  constructor(lab, name, type) {
    this.lab = lab;
    this.name = name;
    this.latest = null;
    this.count = 0;
    this.waiters = [];
    this.topic = new Topic({ ros: lab.ros, name, messageType: type, reconnect_on_close: false });
    this.topic.subscribe((message) => {
      this.latest = message;
      this.count += 1;
      const waiters = this.waiters;
      this.waiters = [];
      for (const resolve of waiters) resolve(message);
    });
  }

  /** The newest message, waiting for the first one (latched topics send it at once). */
  get(timeout = 10) {
    if (this.latest !== null) return Promise.resolve(this.latest);
    const first = new Promise((resolve) => this.waiters.push(resolve));
    return this.lab.guard(first, timeout, `a message on ${this.name}`);
  }
}

/**
 * A connection to one robot of the lab: subscriptions, publishing, and /lab/step.
 * Frames are handled in the order they arrive (roslibjs dispatches each one synchronously),
 * so when a step's answer is handled every subscription holds that tick's message.
 */
class Lab {
  constructor(ros, url) {
    this.ros = ros;
    this.url = url;
    this.subscriptions = new Map();
    this.publishers = new Map();
    this.stepService = new Service({ ros, name: "/lab/step", serviceType: "std_srvs/srv/Trigger" });
    this.refusals = []; // error statuses not yet raised
    this.pending = new Set(); // rejecters of what is being waited for
    this.lost = null; // why the connection closed, once it has
    this.closing = false;
    ros.on("close", (event) => {
      const detail = [event?.code, event?.reason].filter(Boolean).join(": ");
      this.lost = new LabError(
        `the connection to ${url} closed` + (detail ? ` (${detail})` : ""),
      );
      if (!this.closing) for (const reject of [...this.pending]) reject(this.lost);
    });
    ros.on("error", (event) => {
      if (!this.closing) log.warning(`connection error: ${event?.message ?? String(event)}`);
    });
    // Status frames: errors are refusals (a command the lab would not take), raised after
    // the next step's answer as the Python client does; warnings are only logged. A failed
    // call's status repeats what its service_response says, so it is left to the answer.
    ros.transport.on("message", (frame) => {
      if (frame?.op !== "status") return;
      const text = String(frame.msg ?? "");
      if (String(frame.id ?? "").startsWith("call_service:")) return;
      if (frame.level === "error") this.refusals.push(text);
      else log.warning(`the lab says: ${text}`);
    });
  }

  /** Connect to the robot at `url`; an Error saying so when it cannot. */
  static async connect(url) {
    const ros = new Ros({});
    let timer;
    const opened = new Promise((resolve, reject) => {
      const fail = (event) => {
        const reason = event?.message || (event?.code ? `closed with code ${event.code}` : "");
        reject(new LabError(`could not connect to ${url}` + (reason ? ` (${reason})` : "")));
      };
      ros.once("connection", resolve);
      ros.once("error", fail);
      ros.once("close", fail);
      timer = setTimeout(
        () => reject(new LabError(`could not connect to ${url} (no answer within ${CONNECT_TIMEOUT} s)`)),
        CONNECT_TIMEOUT * 1000,
      );
    });
    try {
      await ros.connect(url); // makes the WebSocket (Node 20: the `ws` package's)
      await opened;
    } catch (err) {
      ros.close();
      if (err instanceof LabError) throw err;
      throw new LabError(`could not connect to ${url} (${err?.message ?? err})`);
    } finally {
      clearTimeout(timer);
      ros.removeAllListeners("connection");
      ros.removeAllListeners("error");
      ros.removeAllListeners("close");
    }
    const lab = new Lab(ros, url);
    ros.setStatusLevel("warning"); // errors come back as status frames
    return lab;
  }

  /** `promise`, or a LabError if it takes longer than `timeout` s or the connection closes. */
  guard(promise, timeout, what) {
    if (this.lost) return Promise.reject(this.lost);
    let timer;
    let rejecter;
    const failure = new Promise((_, reject) => {
      rejecter = reject;
      this.pending.add(reject);
      timer = setTimeout(() => reject(new LabError(`${what}: nothing within ${timeout} s`)), timeout * 1000);
    });
    return Promise.race([promise, failure]).finally(() => {
      clearTimeout(timer);
      this.pending.delete(rejecter);
    });
  }

  subscribe(name, type) {
    if (!this.subscriptions.has(name)) this.subscriptions.set(name, new Subscription(this, name, type));
    return this.subscriptions.get(name);
  }

  /** Publish `msg` on `name` (advertised on first use); it does not wait. */
  publish(name, type, msg) {
    let topic = this.publishers.get(name);
    if (topic === undefined) {
      topic = new Topic({ ros: this.ros, name, messageType: type, reconnect_on_close: false });
      this.publishers.set(name, topic);
    }
    topic.publish(msg);
  }

  /**
   * Advance the robot one control tick (/lab/step) and resolve with where it is; rejects
   * with EpisodeOver when the answer says the episode ended on this tick or had ended.
   */
  async step() {
    const answer = new Promise((resolve, reject) => {
      this.stepService.callService(
        {},
        (values) => resolve(values ?? {}),
        (error) => reject(new LabError(`/lab/step failed: ${error}`)),
        STEP_TIMEOUT,
      );
    });
    const values = await this.guard(answer, STEP_TIMEOUT + 2, "calling /lab/step");
    const message = String(values.message ?? "");
    let tick;
    if (values.success) {
      const match = STEP_ANSWER.exec(message);
      if (match) {
        tick = new Tick(Number(match[1]), parseFloat(match[2]), match[3], match[4] ?? "", message);
      } else {
        tick = Tick.fromEpisode(await this.episode(), message);
      }
    } else {
      // "the episode has ended (truncated: ...)": its last tick is the one /lab/episode shows.
      const ended = ENDED_ANSWER.exec(message);
      if (!ended) throw new LabError(`/lab/step failed: ${message}`);
      const last = Tick.fromEpisode(await this.episode());
      tick = new Tick(last.number, last.time, ended[1], ended[2], message);
    }
    if (this.refusals.length) {
      const refusals = this.refusals.splice(0);
      throw new LabError(`the lab refused: ${refusals.join("; ")}`);
    }
    if (!tick.running) throw new EpisodeOver(tick);
    return tick;
  }

  /** The newest lab_msgs/msg/Episode (/lab/episode, latched). */
  episode() {
    return this.subscribe("/lab/episode", "lab_msgs/msg/Episode").get();
  }

  /** Close the connection; resolves once it is closed (or after a second, whatever happens). */
  close() {
    this.closing = true;
    return new Promise((resolve) => {
      if (this.lost) return resolve();
      const timer = setTimeout(resolve, 1000);
      timer.unref();
      this.ros.once("close", () => {
        clearTimeout(timer);
        resolve();
      });
      this.ros.close();
    });
  }
}

// -- the map ----------------------------------------------------------------------------

/** What is known of each cell; unknown cells are not stored. */
class CellMap {
  constructor() {
    this.cells = new Map(); // "x,y" -> [x, y, state]
  }

  get(cell) {
    const entry = this.cells.get(key(cell));
    return entry === undefined ? UNKNOWN : entry[2];
  }

  /** Record `state`; whether it is news. */
  mark(cell, state) {
    const k = key(cell);
    const entry = this.cells.get(k);
    if (entry !== undefined && entry[2] === state) return false;
    this.cells.set(k, [cell[0], cell[1], state]);
    return true;
  }

  /** Forget everything but the floor. */
  keepFloor() {
    for (const [k, entry] of [...this.cells]) if (entry[2] !== FLOOR) this.cells.delete(k);
  }

  /** The cost of stepping into `cell` (which is not known to be wall). */
  cost(cell) {
    if (this.get(cell) === FLOOR) return 1.0;
    return 1.0 + UNKNOWN_COST;
  }

  /**
   * The cheapest cells from `start` (facing `heading`) to `goal`, both included.
   *
   * Dijkstra over (cell, heading): a step forward costs `cost`, a quarter turn TURN_COST.
   * Walls are never entered, and the search stays within a margin of the known cells,
   * since the maze is finite. An empty list: no way. The queue orders entries as Python's
   * heapq orders (cost, cell, heading) tuples, so ties go the same way.
   */
  plan(start, heading, goal) {
    const known = [...[...this.cells.values()].map((e) => [e[0], e[1]]), start, goal];
    const loX = Math.min(...known.map((c) => c[0])) - 2;
    const hiX = Math.max(...known.map((c) => c[0])) + 2;
    const loY = Math.min(...known.map((c) => c[1])) - 2;
    const hiY = Math.max(...known.map((c) => c[1])) + 2;
    const stateKey = (x, y, f) => `${x},${y},${f}`;
    const best = new Map([[stateKey(start[0], start[1], heading), 0.0]]);
    const parent = new Map(); // state key -> [x, y, facing]
    const queue = new Heap();
    queue.push([0.0, start[0], start[1], heading]);
    while (queue.size) {
      const [cost, cx, cy, facing] = queue.pop();
      if (cost > best.get(stateKey(cx, cy, facing))) continue;
      if (cx === goal[0] && cy === goal[1]) {
        const path = [[cx, cy]];
        let state = stateKey(cx, cy, facing);
        while (parent.has(state)) {
          const [px, py, pf] = parent.get(state);
          state = stateKey(px, py, pf);
          const last = path[path.length - 1];
          if (px !== last[0] || py !== last[1]) path.push([px, py]);
        }
        return path.reverse();
      }
      const [dx, dy] = STEPS[facing];
      const ahead = [cx + dx, cy + dy];
      const moves = [
        [ahead[0], ahead[1], facing, this.cost(ahead)],
        [cx, cy, (facing + 1) % 4, TURN_COST],
        [cx, cy, (facing + 3) % 4, TURN_COST],
      ];
      for (const [x, y, f, stepCost] of moves) {
        if (this.get([x, y]) === WALL || !(loX <= x && x <= hiX && loY <= y && y <= hiY)) continue;
        const k = stateKey(x, y, f);
        const previous = best.get(k);
        if (cost + stepCost < (previous === undefined ? Infinity : previous)) {
          best.set(k, cost + stepCost);
          parent.set(k, [cx, cy, facing]);
          queue.push([cost + stepCost, x, y, f]);
        }
      }
    }
    return [];
  }
}

/** A binary min-heap of [cost, x, y, facing], ordered as Python orders the tuples. */
class Heap {
  constructor() {
    this.items = [];
  }

  get size() {
    return this.items.length;
  }

  static less(a, b) {
    for (let i = 0; i < a.length; i++) if (a[i] !== b[i]) return a[i] < b[i];
    return false;
  }

  push(item) {
    const items = this.items;
    items.push(item);
    let i = items.length - 1;
    while (i > 0) {
      const up = (i - 1) >> 1;
      if (!Heap.less(items[i], items[up])) break;
      [items[i], items[up]] = [items[up], items[i]];
      i = up;
    }
  }

  pop() {
    const items = this.items;
    const top = items[0];
    const last = items.pop();
    if (items.length) {
      items[0] = last;
      let i = 0;
      for (;;) {
        const l = 2 * i + 1;
        const r = l + 1;
        let m = i;
        if (l < items.length && Heap.less(items[l], items[m])) m = l;
        if (r < items.length && Heap.less(items[r], items[m])) m = r;
        if (m === i) break;
        [items[i], items[m]] = [items[m], items[i]];
        i = m;
      }
    }
    return top;
  }
}

/** The cells of `path` reached by going straight along `step` from its start. */
function straightRun(path, step) {
  const run = [];
  for (let i = 0; i + 1 < path.length; i++) {
    const [a, b] = [path[i], path[i + 1]];
    if (b[0] - a[0] !== step[0] || b[1] - a[1] !== step[1]) break;
    run.push(b);
  }
  return run;
}

// -- the solver -------------------------------------------------------------------------

/** Drives the robot to the goal cell; `run` ends with the episode (EpisodeOver). */
class MazeSolver {
  constructor(lab, goal) {
    this.lab = lab;
    this.odom = lab.subscribe("/odom", "nav_msgs/msg/Odometry");
    this.bumper = lab.subscribe("/bumper", "lab_msgs/msg/Bumper");
    this.tags = lab.subscribe("/ar_tags", "lab_msgs/msg/ArTagArray");
    this.goal = cellOf(goal.x, goal.y);
    this.map = new CellMap();
    this.pose = { x: 0.0, y: 0.0, yaw: 0.0 }; // in the grid frame (odom corrected for drift)
    this.lastOdom = this.odomPose();
    this.bumped = false;
    this.headOn = false;
    this.news = false; // the map changed since the last plan
    this.time = 0.0;
    this.map.mark([0, 0], FLOOR);
    this.map.mark([1, 0], FLOOR); // the robot starts facing an open neighbour (+x)
    this.map.mark(this.goal, FLOOR);
  }

  /** Subscribe and wait for the first (latched) messages; the solver, ready. */
  static async start(lab) {
    const topics = [
      lab.subscribe("/odom", "nav_msgs/msg/Odometry"),
      lab.subscribe("/bumper", "lab_msgs/msg/Bumper"),
      lab.subscribe("/ar_tags", "lab_msgs/msg/ArTagArray"),
    ];  // not /lab/episode: the step's answer says where the episode is (as in Python)
    const goal = await lab.subscribe("/goal", "geometry_msgs/msg/PointStamped").get();
    for (const topic of topics) await topic.get();
    return new MazeSolver(lab, goal.point);
  }

  // -- sensing ---------------------------------------------------------------------------

  odomPose() {
    const pose = this.odom.latest.pose.pose;
    return [pose.position.x, pose.position.y, yawOf(pose.orientation)];
  }

  /** The forward speed (m/s) odometry measured at the end of the last tick. */
  speed() {
    return Number(this.odom.latest.twist.twist.linear.x);
  }

  /** Command the base for one control tick, step, and take in what it saw. */
  async tick(speed, turn) {
    // The command and the step leave together: nothing is awaited between them.
    this.lab.publish("/cmd_vel", "geometry_msgs/msg/Twist", {
      linear: { x: speed },
      angular: { z: turn },
    });
    this.time = (await this.lab.step()).time;
    // Dead reckoning: this tick's motion in the robot's frame, applied to the pose.
    const [x0, y0, yaw0] = this.lastOdom;
    const [x1, y1, yaw1] = (this.lastOdom = this.odomPose());
    let c = Math.cos(yaw0);
    let s = Math.sin(yaw0);
    const forward = c * (x1 - x0) + s * (y1 - y0);
    const left = -s * (x1 - x0) + c * (y1 - y0);
    const p = this.pose;
    c = Math.cos(p.yaw);
    s = Math.sin(p.yaw);
    p.x += c * forward - s * left;
    p.y += s * forward + c * left;
    p.yaw = wrap(p.yaw + wrap(yaw1 - yaw0));
    const bumper = this.bumper.latest;
    this.bumped = Boolean(bumper.left || bumper.right);
    this.headOn = Boolean(bumper.left && bumper.right);
    for (const tag of this.tags.latest.tags) this.seeTag(tag);
  }

  /** Correct the pose with a tag, and map its wall and the free line of sight. */
  seeTag(tag) {
    const { position, orientation } = tag.pose;
    // Into the wall (the tag's z) and the tag's centre, in base_link (optical z forward,
    // x right, y down).
    const { x: qx, y: qy, z: qz, w: qw } = orientation;
    const intoForward = 1 - 2 * (qx * qx + qy * qy); // R[2][2]
    const intoLeft = -2 * (qx * qz + qw * qy); // -R[0][2]
    const bearing = Math.atan2(intoLeft, intoForward);
    const forward = CAMERA + position.z;
    const left = -position.x;
    // The face's normal is along a grid axis: snap it, which fixes the heading.
    const p = this.pose;
    const axis = pyRound((p.yaw + bearing) / (Math.PI / 2));
    const yaw = wrap((axis * Math.PI) / 2 - bearing);
    if (Math.abs(wrap(yaw - p.yaw)) > 0.3) {
      log.warning(`${seconds(this.time)} s: ignored tag ${tag.id}: heading off by too much`);
      return;
    }
    const c = Math.cos(yaw);
    const s = Math.sin(yaw);
    const tx = p.x + c * forward - s * left;
    const ty = p.y + s * forward + c * left;
    // The tag is centred on a face: on a cell boundary across the axis, at a cell's centre
    // along the face.
    const [nx, ny] = STEPS[pyMod(axis, 4)];
    let trueX;
    let trueY;
    if (nx) {
      trueX = (Math.floor(tx / CELL) + 0.5) * CELL;
      trueY = pyRound(ty / CELL) * CELL;
    } else {
      trueX = pyRound(tx / CELL) * CELL;
      trueY = (Math.floor(ty / CELL) + 0.5) * CELL;
    }
    p.x = p.x + trueX - tx;
    p.y = p.y + trueY - ty;
    p.yaw = yaw;
    this.learn(cellOf(trueX + nx * HALF, trueY + ny * HALF), WALL);
    this.learn(cellOf(trueX - nx * HALF, trueY - ny * HALF), FLOOR);
    // The line of sight from the camera crosses floor only; skip points near edges.
    const cx = p.x + c * CAMERA;
    const cy = p.y + s * CAMERA;
    const length = Math.hypot(trueX - cx, trueY - cy);
    const points = Math.trunc(length / 0.05);
    for (let k = 0; k < points; k++) {
      const f = (k * 0.05) / length;
      const x = cx + f * (trueX - cx);
      const y = cy + f * (trueY - cy);
      const u = x / CELL - pyRound(x / CELL);
      const v = y / CELL - pyRound(y / CELL);
      if (Math.max(Math.abs(u), Math.abs(v)) < 0.5 - 0.08 / CELL) this.learn(cellOf(x, y), FLOOR);
    }
  }

  learn(cell, state) {
    if (this.map.mark(cell, state)) this.news = true;
  }

  // -- moving ----------------------------------------------------------------------------

  cell() {
    return cellOf(this.pose.x, this.pose.y);
  }

  heading() {
    return pyMod(pyRound(this.pose.yaw / (Math.PI / 2)), 4);
  }

  /** Turn in place until facing `heading` (an index of STEPS). */
  async turnTo(heading) {
    const target = (heading * Math.PI) / 2;
    const deadline = this.time + GIVE_UP;
    while (this.time < deadline) {
      const error = wrap(target - this.pose.yaw);
      if (Math.abs(error) < ALIGNED) return;
      await this.tick(0.0, Math.max(-TURN_SPEED, Math.min(TURN_SPEED, HEADING_GAIN * error)));
    }
  }

  /**
   * Drive from `start`'s centre along `heading`, aiming `cells` ahead.
   *
   * On entering each cell it re-plans: the run is stretched or cut short (to stop at a
   * centre, where it can turn). A bump marks the cell ahead as wall and backs the robot
   * up to the centre of the cell it came from.
   */
  async drive(heading, start, cells) {
    const [dx, dy] = STEPS[heading];
    let target = cells;
    let entered = 0; // the furthest cell along the run the robot's centre has entered
    const deadline = this.time + GIVE_UP * (cells + 1);
    while (this.time < deadline) {
      const p = this.pose;
      const along = (p.x - start[0] * CELL) * dx + (p.y - start[1] * CELL) * dy;
      const across = -(p.x - start[0] * CELL) * dy + (p.y - start[1] * CELL) * dx;
      if (this.bumped) {
        await this.bump(heading, start, along);
        return;
      }
      const front = along + RADIUS;
      for (let k = entered + 1; k < target + 1; k++) {
        // cells the front has entered: floor
        if (front > k * CELL - HALF + 0.03) this.learn([start[0] + k * dx, start[1] + k * dy], FLOOR);
      }
      const here = pyRound(along / CELL);
      if (here > entered && along > here * CELL - HALF + 0.05) {
        entered = here;
        target = entered + this.straight(heading);
      } else if (this.news) {
        // a tag showed something: does the run still hold?
        target = entered + this.straight(heading);
      }
      const remaining = target * CELL - along;
      if (Math.abs(remaining) < ARRIVED && Math.abs(this.speed()) < 0.05) return;
      let speed = Math.min(
        MAX_SPEED,
        Math.sqrt(2 * BRAKE * Math.abs(remaining)),
        2.5 * Math.abs(remaining),
      );
      speed = copysign(speed, remaining);
      const ahead = [start[0] + (entered + 1) * dx, start[1] + (entered + 1) * dy];
      const toTouch = (entered + 1) * CELL - HALF - front;
      if (this.map.get(ahead) !== FLOOR && entered < target) {
        // Reach the unknown cell at probing speed.
        const limit = Math.sqrt(
          PROBE_SPEED * PROBE_SPEED + 2 * BRAKE * Math.max(0.0, toTouch - 0.05),
        );
        speed = Math.min(speed, limit);
      }
      const desired = (heading * Math.PI) / 2 - Math.max(-0.4, Math.min(0.4, TRACK_GAIN * across));
      const error = wrap(desired - p.yaw);
      speed *= Math.max(0.0, Math.cos(error));
      await this.tick(speed, Math.max(-TURN_SPEED, Math.min(TURN_SPEED, HEADING_GAIN * error)));
    }
  }

  /** How many cells the current plan goes straight on along `heading` from here. */
  straight(heading) {
    return straightRun(this.plan(), STEPS[heading]).length;
  }

  /** The front touched a wall: map it, fix the position, back up to a centre. */
  async bump(heading, start, along) {
    const [dx, dy] = STEPS[heading];
    const k = pyRound((along + RADIUS + HALF) / CELL); // the cell whose near face was touched
    const wall = [start[0] + k * dx, start[1] + k * dy];
    this.learn(wall, WALL);
    if (this.headOn) {
      // the front is on the face: the position along the run is known
      const shift = k * CELL - HALF - RADIUS - along;
      this.pose.x += shift * dx;
      this.pose.y += shift * dy;
    }
    log.info(`${seconds(this.time)} s: bumped into ${show(wall)}`);
    const back = [start[0] + (k - 1) * dx, start[1] + (k - 1) * dy];
    await this.backTo(back, heading);
  }

  /** Reverse along `heading`'s line to `cell`'s centre. */
  async backTo(cell, heading) {
    const [dx, dy] = STEPS[heading];
    const deadline = this.time + GIVE_UP;
    while (this.time < deadline) {
      const p = this.pose;
      const remaining = (cell[0] * CELL - p.x) * dx + (cell[1] * CELL - p.y) * dy;
      const across = -(p.x - cell[0] * CELL) * dy + (p.y - cell[1] * CELL) * dx;
      if (Math.abs(remaining) < ARRIVED && Math.abs(this.speed()) < 0.05) return;
      const speed = Math.min(
        MAX_SPEED,
        Math.sqrt(2 * BRAKE * Math.abs(remaining)),
        2.5 * Math.abs(remaining),
      );
      // Reversing, steer the back onto the line: the sign of the correction flips.
      const desired = (heading * Math.PI) / 2 + Math.max(-0.4, Math.min(0.4, TRACK_GAIN * across));
      const error = wrap(desired - p.yaw);
      await this.tick(copysign(speed, remaining), HEADING_GAIN * error);
    }
  }

  /** The way from here to the goal on the map (two cells at least). */
  plan() {
    this.news = false;
    let path = this.map.plan(this.cell(), this.heading(), this.goal);
    if (path.length < 2) {
      // Walls all round: something was mapped wrong. Keep only the floor, retry.
      log.warning(`${seconds(this.time)} s: no way to the goal; forgetting the walls`);
      this.map.keepFloor();
      path = this.map.plan(this.cell(), this.heading(), this.goal);
    }
    return path;
  }

  /** Plan, turn, drive; again and again until the episode ends (EpisodeOver). */
  async run() {
    for (;;) {
      const here = this.cell();
      const path = this.plan();
      if (path.length < 2) throw new Error(`no way from ${show(here)} to the goal ${show(this.goal)}`);
      const step = [path[1][0] - here[0], path[1][1] - here[1]];
      const heading = STEPS.findIndex((s) => s[0] === step[0] && s[1] === step[1]);
      if (heading < 0) throw new Error(`the plan's next cell ${show(path[1])} is not next to ${show(here)}`);
      log.info(
        `${seconds(this.time)} s: at ${show(here)}, heading for ${show(path[1])}, ` +
          `${path.length - 1} cells to go`,
      );
      const run = straightRun(path, step);
      const facing = this.heading();
      if (heading === (facing + 2) % 4 && run.every((c) => this.map.get(c) === FLOOR)) {
        await this.backTo(run[run.length - 1], facing); // known floor behind: reverse, no U-turn
      } else {
        await this.turnTo(heading);
        await this.drive(heading, here, run.length);
      }
    }
  }
}

// -- main -------------------------------------------------------------------------------

/** Where the lab is: in a sandbox, the bridge's own unix socket (one hop fewer than the
 * relay behind LAB_BRIDGE_URL; the `ws` package takes `ws+unix:` URLs), else the URL. */
function bridgeUrl() {
  const socket = process.env.LAB_BRIDGE_SOCKET;
  if (socket && existsSync(socket)) return `ws+unix://${socket}:/`;
  return process.env.LAB_BRIDGE_URL || DEFAULT_URL;
}

async function main() {
  const url = bridgeUrl();
  let lab;
  try {
    lab = await Lab.connect(url);
  } catch (err) {
    console.error(`maze: ${err.message}`);
    return 1;
  }
  try {
    const solver = await MazeSolver.start(lab);
    log.info(`goal cell ${show(solver.goal)}`);
    try {
      await solver.run();
    } catch (err) {
      if (!(err instanceof EpisodeOver)) throw err;
      log.info(`episode over at ${seconds(err.tick.time)} s: ${err.tick.message}`);
    }
    return 0;
  } catch (err) {
    console.error(`maze: ${err instanceof LabError ? err.message : err?.stack ?? err}`);
    return 1;
  } finally {
    await lab.close();
  }
}

process.exitCode = await main();
// Everything is closed, so Node exits by itself; this only guards against a handle left open.
setTimeout(() => process.exit(), 2000).unref();
