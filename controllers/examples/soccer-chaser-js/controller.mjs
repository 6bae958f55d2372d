// Chase the ball and push it into the opponents' goal (the lab's soccer-1v1).
//
// A JavaScript (Node.js 20, ESM) port of controllers/examples/soccer-chaser/controller.py,
// talking to the lab with roslibjs (npm `roslib` 2.x): the same policy, the same constants,
// the same arithmetic, operation for operation.
//
// A BoxHead walker rolls toward its own -x (`roll`), turns with a torque (`steer`, positive
// clockwise seen from above, with momentum: the policy damps it with the gyro's yaw rate)
// and kicks (`kick`). Everything it needs is ego-centric, in the walker's frame: where the
// ball is (`ball_ego_position`), where the opponents' goal is (`opponent_goal_mid`), and how
// fast it turns (`sensors_gyro`); docs/tasks.md, "Soccer".
//
// The plan, each tick: with the ball ahead and the goal beyond it, roll at the ball and kick
// when both line up; otherwise roll to a point two metres behind the ball on the line from
// the goal, going round the ball when it is in the way (pushing it from the wrong side
// scores for the other team).
//
// It plays its team's player 0, as a team sees its own topics: /player_0/... (alone, it
// plays home: the record names them /home/player_0/...). Lockstep: each tick it publishes
// its action and calls /lab/step (std_srvs/srv/Trigger) at once; the lab steps, publishes
// the tick's observations and only then answers, so when the answer arrives the newest
// message of each subscription is this tick's. Nothing random or timed in any decision: the
// same seed gives the same leg.

import { existsSync } from "node:fs";
import { pathToFileURL } from "node:url";
import { Ros, Service, Topic } from "roslib";

const ARRAY = "std_msgs/msg/Float64MultiArray";
const PLAYER = "/player_0/"; // this team's player 0 (its side's: home, alone)
const BEHIND = 2.0; // metres behind the ball to line up from
const LINED_UP = 0.85; // cosine between the way to the ball and the ball's way to the goal
const ROUND = 1.5; // metres: closer than this to the path, the ball is in the way
const GAIN = 3.0; // steering: on the angle to the target
const DAMPING = 0.5; // steering: on the turn rate

const DEFAULT_URL = "ws://127.0.0.1:9090";
const CONNECT_TIMEOUT = 10; // s (wall clock): a guard, never a decision
const STEP_TIMEOUT = 120; // s the lab may take to answer /lab/step (in a match, the other team may take a minute to start)
// The lab's /lab/step answers: "tick 399 at 9.975 s: succeeded: home scored at 9.975 s: 1-0".
const STEP_ANSWER = /^tick (\d+) at ([0-9.]+) s: (\w+)(?:: ([\s\S]*))?$/;
// Once it has ended: "the episode has ended (succeeded: home scored ...)".
const ENDED_ANSWER = /^[\s\S]*\((\w+): ([\s\S]*)\)$/;

// -- the policy -------------------------------------------------------------------------
//
// Two-vectors as [x, y]; the Python's NumPy operations spelled out in the same order:
// np.dot(a, b) is a[0] * b[0] + a[1] * b[1], np.linalg.norm(a) the square root of that.
// The results may differ in their last bits (OpenBLAS fuses the dot's second product,
// V8's Math.atan2 is not glibc's): README.md.

const dot = (a, b) => a[0] * b[0] + a[1] * b[1];
const norm = (a) => Math.sqrt(dot(a, a));
const scale = (k, a) => [k * a[0], k * a[1]];
const minus = (a, b) => [a[0] - b[0], a[1] - b[1]];
const plus = (a, b) => [a[0] + b[0], a[1] + b[1]];
const clip = (low, high, x) => Math.max(low, Math.min(high, x));

/** A point in the walker's frame as [ahead, left]: it rolls toward its -x. */
function ahead(ego) {
  return [-ego[0], -ego[1]];
}

/** Roll, steer and kick for one tick. */
export function act(ballEgo, goalEgo, gyro) {
  const ball = ahead(ballEgo);
  const goal = ahead(goalEgo);
  let toGoal = minus(goal, ball);
  const length = norm(toGoal) + 1e-9;
  toGoal = [toGoal[0] / length, toGoal[1] / length];
  const distance = norm(ball);
  const reach = distance + 1e-9;
  const linedUp = dot([ball[0] / reach, ball[1] / reach], toGoal) > LINED_UP;
  let target;
  if (linedUp || distance < 1.0) {
    target = ball;
  } else {
    target = minus(ball, scale(BEHIND, toGoal));
    const along = clip(0.0, 1.0, dot(ball, target) / (dot(target, target) + 1e-9));
    if (norm(minus(ball, scale(along, target))) < ROUND) {
      // the ball in the way: round it
      let side = [-toGoal[1], toGoal[0]];
      if (dot([-ball[0], -ball[1]], side) < 0) side = [-side[0], -side[1]]; // on the side the walker is
      target = plus(ball, scale(2.0, side));
    }
  }
  const angle = Math.atan2(target[1], target[0]);
  const steer = clip(-1.0, 1.0, -(GAIN * angle - DAMPING * gyro[2]));
  const roll = Math.abs(angle) < 1.0 ? 1.0 : 0.4; // slow down to turn
  const facingBall = Math.abs(Math.atan2(ball[1], ball[0])) < 0.4;
  const facingGoal = Math.abs(Math.atan2(goal[1], goal[0])) < 0.3;
  const kick = distance < 1.2 && facingBall && facingGoal ? 1.0 : 0.0;
  return [roll, steer, kick];
}

// -- the lab, through roslibjs ----------------------------------------------------------

class LabError extends Error {}

/** The episode has ended: `sentence` is what the lab said of its last tick. */
class EpisodeOver extends LabError {
  constructor(sentence) {
    super(`the episode is over: ${sentence}`);
    this.sentence = sentence;
  }
}

/** One topic's messages as they arrive: `latest` (null before the first). */
class Subscription {
  constructor(lab, name, type) {
    this.lab = lab;
    this.name = name;
    this.latest = null;
    this.waiters = [];
    this.topic = new Topic({ ros: lab.ros, name, messageType: type, reconnect_on_close: false });
    this.topic.subscribe((message) => {
      this.latest = message;
      const waiters = this.waiters.splice(0);
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
 * A connection to the lab: subscriptions, publishing, and /lab/step. roslibjs handles
 * frames in the order they arrive, so when a step's answer is handled every subscription
 * holds that tick's message.
 */
class Lab {
  constructor(ros, url) {
    this.ros = ros;
    this.url = url;
    this.publishers = new Map();
    this.stepService = new Service({ ros, name: "/lab/step", serviceType: "std_srvs/srv/Trigger" });
    this.refusals = []; // error statuses not yet raised
    this.pending = new Set(); // rejecters of what is being waited for
    this.lost = null; // why the connection closed, once it has
    this.closing = false;
    ros.on("close", (event) => {
      const detail = [event?.code, event?.reason].filter(Boolean).join(": ");
      this.lost = new LabError(`the connection to ${url} closed` + (detail ? ` (${detail})` : ""));
      if (!this.closing) for (const reject of [...this.pending]) reject(this.lost);
    });
    ros.on("error", (event) => {
      if (!this.closing) console.error(`chaser: connection error: ${event?.message ?? event}`);
    });
    // Error statuses are refusals (a command the lab would not take), raised after the next
    // step's answer as the Python client does; a failed call's status repeats its answer.
    ros.transport.on("message", (frame) => {
      if (frame?.op !== "status" || String(frame.id ?? "").startsWith("call_service:")) return;
      if (frame.level === "error") this.refusals.push(String(frame.msg ?? ""));
      else console.error(`chaser: the lab says: ${frame.msg}`);
    });
  }

  /** Connect to the lab at `url`; a LabError saying so when it cannot. */
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
      await ros.connect(url); // Node 20 has no global WebSocket: roslib uses the `ws` package
      await opened;
    } catch (err) {
      ros.close();
      if (err instanceof LabError) throw err;
      throw new LabError(`could not connect to ${url} (${err?.message ?? err})`);
    } finally {
      clearTimeout(timer);
      for (const event of ["connection", "error", "close"]) ros.removeAllListeners(event);
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
    return new Subscription(this, name, type);
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

  /** Advance one tick (/lab/step); rejects with EpisodeOver when the episode has ended. */
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
    let running;
    if (values.success) {
      const match = STEP_ANSWER.exec(message);
      // An answer in another form: /lab/episode says where the episode is.
      running = match ? match[3] === "running" : (await this.episode()).status === "running";
    } else if (ENDED_ANSWER.test(message)) {
      running = false; // "the episode has ended (...)"
    } else {
      throw new LabError(`/lab/step failed: ${message}`);
    }
    if (this.refusals.length) throw new LabError(`the lab refused: ${this.refusals.splice(0).join("; ")}`);
    if (!running) throw new EpisodeOver(message);
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

// -- main -------------------------------------------------------------------------------

/** Where the lab is: in a sandbox, the bridge's own unix socket (the `ws` package takes
 * `ws+unix:` URLs), else LAB_BRIDGE_URL. */
function bridgeUrl() {
  const socket = process.env.LAB_BRIDGE_SOCKET;
  if (socket && existsSync(socket)) return `ws+unix://${socket}:/`;
  return process.env.LAB_BRIDGE_URL || DEFAULT_URL;
}

/** Play until the episode ends; the exit status (0 however the leg went). */
async function main() {
  const url = bridgeUrl();
  let lab;
  try {
    lab = await Lab.connect(url);
  } catch (err) {
    console.error(`chaser: ${err.message}`);
    return 1;
  }
  try {
    const ball = lab.subscribe(PLAYER + "observation/ball_ego_position", ARRAY);
    const goal = lab.subscribe(PLAYER + "observation/opponent_goal_mid", ARRAY);
    const gyro = lab.subscribe(PLAYER + "observation/sensors_gyro", ARRAY);
    for (;;) {
      const command = act((await ball.get()).data, (await goal.get()).data, (await gyro.get()).data);
      // The command and the step leave together: nothing is awaited between them.
      lab.publish(PLAYER + "action", ARRAY, { data: command });
      try {
        await lab.step();
      } catch (err) {
        if (!(err instanceof EpisodeOver)) throw err;
        console.log(`episode over: ${err.sentence}`);
        return 0;
      }
    }
  } catch (err) {
    console.error(`chaser: ${err instanceof LabError ? err.message : (err?.stack ?? err)}`);
    return 1;
  } finally {
    await lab.close();
  }
}

// Run when started (node controller.mjs); imported, it only gives `act`.
if (process.argv[1] && import.meta.url === pathToFileURL(process.argv[1]).href) {
  process.exitCode = await main();
  // Everything is closed, so Node exits by itself; this only guards against a handle left open.
  setTimeout(() => process.exit(), 2000).unref();
}
