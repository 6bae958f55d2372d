// Shared plumbing for the roslibjs client scripts that tests/integration/test_roslibjs.py runs.
//
// Each script is `node SCRIPT.mjs URL [SCENARIO ...]`: it runs the named scenarios (all of
// them when none is named) against the bridge at URL with the real roslibjs, and prints one
// JSON object on stdout: {"scenarios": {NAME: observations}, "ros_errors": [...]}. Every wait
// is bounded; a timeout or a broken expectation exits with status 1 and a sentence on stderr.
// The assertions live in Python; the scripts only observe.

import { Ros, Service } from "roslib";

export const WAIT_MS = 5000; // the longest any single wait may take
const DEADLINE_MS = 45000; // the whole script, whatever happens

/** A scenario could not observe what it came for (a timeout, an unexpected failure). */
export class Failure extends Error {}

/** `promise`, or a Failure naming `what` if it takes longer than `ms`. */
export function withTimeout(promise, what, ms = WAIT_MS) {
  let timer;
  const timeout = new Promise((_, reject) => {
    timer = setTimeout(() => {
      const text = typeof what === "function" ? what() : what;
      reject(new Failure(`timed out after ${ms} ms waiting for ${text}`));
    }, ms);
  });
  return Promise.race([promise, timeout]).finally(() => clearTimeout(timer));
}

/** Run a callback-style roslibjs call; resolve with its success value, fail on its error. */
export function succeeds(what, start, ms = WAIT_MS) {
  const done = new Promise((resolve, reject) => {
    start(resolve, (err) => reject(new Failure(`${what} failed: ${JSON.stringify(err)}`)));
  });
  return withTimeout(done, what, ms);
}

/** Run a callback-style roslibjs call; resolve with {ok, value} or {ok: false, error}. */
export function settles(what, start, ms = WAIT_MS) {
  const done = new Promise((resolve) => {
    start(
      (value) => resolve({ ok: true, value: plain(value) }),
      (error) => resolve({ ok: false, error: plain(error) }),
    );
  });
  return withTimeout(done, what, ms);
}

/** Items that arrive over time (messages, statuses), and bounded waits for enough of them. */
export class Inbox {
  constructor(label) {
    this.label = label;
    this.items = [];
    this.times = []; // performance.now() of each arrival, in ms
    this.waiters = [];
  }

  push(item) {
    this.items.push(item);
    this.times.push(performance.now());
    for (const waiter of [...this.waiters]) {
      if (waiter.test(this.items)) {
        this.waiters.splice(this.waiters.indexOf(waiter), 1);
        waiter.resolve(this.items);
      }
    }
  }

  /** Resolve once `test(items)` holds; on timeout, say what had arrived. */
  until(what, test, ms = WAIT_MS) {
    if (test(this.items)) return Promise.resolve(this.items);
    const waiting = new Promise((resolve) => this.waiters.push({ test, resolve }));
    return withTimeout(
      waiting,
      () => `${what} on ${this.label} (got ${JSON.stringify(this.items.map(plain))})`,
      ms,
    );
  }

  count(n, ms = WAIT_MS) {
    return this.until(`${n} item(s)`, (items) => items.length >= n, ms);
  }
}

/** A value as JSON can carry it: typed arrays are marked, BigInts become strings. */
export function plain(value) {
  if (typeof value === "bigint") return value.toString();
  if (ArrayBuffer.isView(value)) {
    return { typed_array: value.constructor.name, values: Array.from(value, plain) };
  }
  if (Array.isArray(value)) return value.map(plain);
  if (value instanceof Error) return String(value);
  if (value !== null && typeof value === "object") {
    return Object.fromEntries(Object.entries(value).map(([k, v]) => [k, plain(v)]));
  }
  return value;
}

const connections = [];
const rosErrors = [];

/**
 * A connected roslibjs `Ros`. Its `statuses` inbox holds every status frame the bridge
 * sends it (roslibjs itself routes them to "status" or "status:ID" events).
 */
export async function connect(url, label) {
  const ros = new Ros({ url });
  ros.label = label;
  connections.push(ros);
  ros.on("error", (err) => rosErrors.push(`${label}: ${err?.message ?? String(err)}`));
  const opened = new Promise((resolve) => ros.once("connection", resolve));
  await withTimeout(opened, `${label} to connect`);
  ros.statuses = new Inbox(`${label} statuses`);
  ros.transport.on("message", (frame) => {
    if (frame.op === "status") ros.statuses.push(frame);
  });
  return ros;
}

/**
 * A round trip through the bridge on `ros`'s connection. The bridge handles each
 * connection's frames in order and answers /rosapi itself at once, so when this resolves
 * every frame `ros` sent before has been handled, and every frame the bridge queued for
 * `ros` before the answer (messages, statuses) has arrived.
 */
export function roundTrip(ros) {
  const probe = new Service({ ros, name: "/rosapi/get_time", serviceType: "rosapi/GetTime" });
  return succeeds("a /rosapi/get_time round trip", (ok, fail) => probe.callService({}, ok, fail));
}

/** Run the scenarios named on the command line (or all) and print what they observed. */
export function run(scenarios) {
  const [url, ...names] = process.argv.slice(2);
  const deadline = setTimeout(() => {
    process.stderr.write(`the script did not finish within ${DEADLINE_MS} ms\n`);
    process.exit(2);
  }, DEADLINE_MS);
  deadline.unref();
  main(url, names.length ? names : Object.keys(scenarios), scenarios).then(
    (output) => {
      process.stdout.write(`${JSON.stringify(output)}\n`, () => process.exit(0));
    },
    (err) => {
      const text = err instanceof Failure ? err.message : err?.stack ?? String(err);
      process.stderr.write(`${text}\n`);
      if (rosErrors.length) process.stderr.write(`roslibjs errors: ${rosErrors.join("; ")}\n`);
      process.exit(1);
    },
  );
}

async function main(url, names, scenarios) {
  if (!url) throw new Failure("usage: node SCRIPT.mjs ws://HOST:PORT [SCENARIO ...]");
  const unknown = names.filter((name) => !(name in scenarios));
  if (unknown.length) throw new Failure(`no scenario ${unknown.join(", ")} in this script`);
  const observed = {};
  for (const name of names) {
    try {
      observed[name] = plain(await scenarios[name](url));
    } catch (err) {
      if (err instanceof Failure) err.message = `${name}: ${err.message}`;
      throw err;
    } finally {
      for (const ros of connections.splice(0)) ros.close();
    }
  }
  return { scenarios: observed, ros_errors: rosErrors };
}
