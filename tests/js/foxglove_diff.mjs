// One side of a differential test: Foxglove's own client (npm @foxglove/ws-protocol 0.8,
// unmodified) against any server of Foxglove's WebSocket protocol, the lab's bridge or a
// Foxglove SDK server; tests/integration/test_foxglove_differential.py runs it against both
// and compares what it observed.
//
//   node foxglove_diff.mjs ws://HOST:PORT/PATH SCENARIO
//
// The subprotocols offered are FOXGLOVE_SUBPROTOCOLS (comma-separated; foxglove.sdk.v1 by
// default). FOXGLOVE_TWIST is a JSON object {schema, value, count}: the Twist the publish
// scenario advertises on /cmd_vel in CDR and sends `count` times (on the lab, the robot's
// first command starts a new episode: publish runs after observe). Output as harness.mjs.

import rosmsg from "@foxglove/rosmsg";
import serialization from "@foxglove/rosmsg2-serialization";
import wsProtocol from "@foxglove/ws-protocol";
import WebSocket from "ws";

import { Failure, Inbox, run, withTimeout } from "./harness.mjs";

// CommonJS packages: their exports are the default export's fields under Node 20.
const { parse } = rosmsg;
const { MessageReader, MessageWriter } = serialization;
const { FoxgloveClient } = wsProtocol;

const OFFERED = (process.env.FOXGLOVE_SUBPROTOCOLS ?? "foxglove.sdk.v1").split(",");
const MESSAGES = 8; // /odom messages to observe
const SEND_GAP_MS = 100; // between two Twists: well under /cmd_vel's rate limit

const sleep = (ms) => new Promise((resolve) => setTimeout(resolve, ms));

function hex(view) {
  return Buffer.from(view.buffer, view.byteOffset, view.byteLength).toString("hex");
}

/** A FoxgloveClient on a new socket, with inboxes and the order of binary frames. */
function client(url) {
  const ws = new WebSocket(url, OFFERED);
  const foxglove = new FoxgloveClient({ ws });
  const inbox = {};
  for (const event of ["serverInfo", "status", "advertise", "message", "time"]) {
    inbox[event] = new Inbox(event);
    foxglove.on(event, (value) => inbox[event].push(value));
  }
  const order = []; // ["time" | "message", timestamp] as they arrived
  foxglove.on("time", (t) => order.push(["time", t.timestamp.toString()]));
  foxglove.on("message", (m) => order.push(["message", m.timestamp.toString()]));
  const errors = [];
  foxglove.on("error", (err) => errors.push(err?.message ?? String(err)));
  const handshake = withTimeout(
    new Promise((resolve) => {
      ws.once("open", () => resolve({ opened: true, protocol: ws.protocol }));
      ws.once("unexpected-response", (_request, response) => {
        response.resume();
        resolve({ opened: false, status: response.statusCode });
      });
    }),
    "the handshake",
  );
  return { ws, foxglove, inbox, order, errors, handshake };
}

/** A client whose handshake succeeded. */
async function opened(url) {
  const c = client(url);
  const { opened: ok, status } = await c.handshake;
  if (!ok) throw new Failure(`the server refused the handshake (HTTP ${status})`);
  return c;
}

const scenarios = {
  /** What a server says in the handshake to a client offering FOXGLOVE_SUBPROTOCOLS. */
  async handshake(url) {
    const c = client(url);
    const result = await c.handshake;
    if (result.opened) {
      const [info] = await c.inbox.serverInfo.count(1);
      result.serverInfo = info;
      c.foxglove.close();
    } else {
      c.ws.terminate(); // no socket to close: the request is dropped
    }
    return result;
  },

  /** Server info, the /odom channel, its messages decoded, and the Time frames around them. */
  async observe(url) {
    const c = await opened(url);
    const [info] = await c.inbox.serverInfo.count(1);
    const all = () => c.inbox.advertise.items.flat();
    const hasOdom = () => all().some((ch) => ch.topic === "/odom");
    await c.inbox.advertise.until("the /odom channel", hasOdom);
    const odom = all().find((ch) => ch.topic === "/odom");
    const subscription = c.foxglove.subscribe(odom.id);
    const mine = (items) => items.filter((m) => m.subscriptionId === subscription);
    await c.inbox.message.until(
      `${MESSAGES} /odom messages`,
      (items) => mine(items).length >= MESSAGES,
    );
    const reader = new MessageReader(parse(odom.schema, { ros2: true }));
    const messages = mine(c.inbox.message.items).map((m) => ({
      timestamp: m.timestamp.toString(),
      hex: hex(m.data),
      value: reader.readMessage(m.data),
      trailing: reader.lastReadHadTrailingBytes(),
    }));
    const stamps = messages.map((m) => m.timestamp);
    const told = (items) => new Set(items.map((t) => t.timestamp.toString()));
    await c.inbox.time.until("a Time frame of each message's time", (items) =>
      stamps.every((stamp) => told(items).has(stamp)),
    );
    const observed = {
      protocol: c.ws.protocol,
      info,
      channel: odom,
      subscription,
      messages,
      order: c.order,
      statuses: c.inbox.status.items,
      errors: c.errors,
    };
    c.foxglove.close();
    return observed;
  },

  /** FOXGLOVE_TWIST advertised on /cmd_vel in CDR and sent, `count` times. */
  async publish(url) {
    const twist = JSON.parse(process.env.FOXGLOVE_TWIST ?? "null");
    if (!twist) throw new Failure("publish needs FOXGLOVE_TWIST");
    const c = await opened(url);
    await c.inbox.serverInfo.count(1);
    const channel = c.foxglove.advertise({
      topic: "/cmd_vel",
      encoding: "cdr",
      schemaName: "geometry_msgs/msg/Twist",
      schema: twist.schema,
      schemaEncoding: "ros2msg",
    });
    const data = new MessageWriter(parse(twist.schema, { ros2: true })).writeMessage(twist.value);
    for (let i = 0; i < twist.count; i += 1) {
      c.foxglove.sendMessage(channel, data);
      await sleep(SEND_GAP_MS);
    }
    const observed = { sent: hex(data), statuses: c.inbox.status.items, errors: c.errors };
    c.foxglove.close();
    return observed;
  },
};

run(scenarios);
