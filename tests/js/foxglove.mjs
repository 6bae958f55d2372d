// Foxglove's own client (npm @foxglove/ws-protocol 0.8, unmodified) against a live robot of
// the lab, its messages decoded with Foxglove's ROS 2 reader (@foxglove/rosmsg2-serialization).
//
//   node foxglove.mjs ws://HOST:PORT/robots/NAME SCENARIO ...
//
// The subprotocols offered are FOXGLOVE_SUBPROTOCOLS (comma-separated; by default
// foxglove.sdk.v1, the name today's app and the Foxglove SDK use). The output follows
// harness.mjs: one JSON object of observations per scenario; the assertions are in
// tests/integration/test_foxglove.py. Every error event of a client fails the script.

import rosmsg from "@foxglove/rosmsg";
import serialization from "@foxglove/rosmsg2-serialization";
import wsProtocol from "@foxglove/ws-protocol";
import WebSocket from "ws";

import { Failure, Inbox, WAIT_MS, run, withTimeout } from "./harness.mjs";

// CommonJS packages: their exports are the default export's fields under Node 20.
const { parse } = rosmsg;
const { MessageReader, MessageWriter } = serialization;
const { FoxgloveClient } = wsProtocol;

const OFFERED = (process.env.FOXGLOVE_SUBPROTOCOLS ?? "foxglove.sdk.v1").split(",");
const clients = [];

/** A connected FoxgloveClient with inboxes of what the lab sent it. */
async function connect(url, label, { key } = {}) {
  const ws = new WebSocket(key ? `${url}?key=${encodeURIComponent(key)}` : url, OFFERED);
  const client = new FoxgloveClient({ ws });
  client.ws = ws;
  client.label = label;
  clients.push(client);
  const inboxes = {};
  for (const event of [
    "serverInfo", "status", "advertise", "unadvertise", "advertiseServices", "message", "time",
    "parameterValues", "serviceCallResponse", "serviceCallFailure", "connectionGraphUpdate",
    "close",
  ]) {
    inboxes[event] = new Inbox(`${label} ${event}`);
    client.on(event, (value) => inboxes[event].push(value));
  }
  client.errors = [];
  client.on("error", (err) => client.errors.push(`${label}: ${err?.message ?? String(err)}`));
  client.inbox = inboxes;
  await withTimeout(
    new Promise((resolve, reject) => {
      ws.once("open", resolve);
      ws.once("error", reject);
    }),
    `${label} to connect`,
  );
  return client;
}

function closeAll() {
  const errors = clients.flatMap((client) => client.errors);
  for (const client of clients.splice(0)) client.close();
  if (errors.length) throw new Failure(`the Foxglove client reported errors: ${errors.join("; ")}`);
}

/** Every channel advertised so far, by topic. */
async function channels(client, wanted = []) {
  const all = () => client.inbox.advertise.items.flat();
  await client.inbox.advertise.until(`channels ${wanted}`, () =>
    wanted.every((topic) => all().some((c) => c.topic === topic)),
  );
  return Object.fromEntries(all().map((c) => [c.topic, c]));
}

async function services(client, wanted = []) {
  const all = () => client.inbox.advertiseServices.items.flat();
  await client.inbox.advertiseServices.until(`services ${wanted}`, () =>
    wanted.every((name) => all().some((s) => s.name === name)),
  );
  return Object.fromEntries(all().map((s) => [s.name, s]));
}

const readers = new Map();
function reader(schema) {
  if (!readers.has(schema)) readers.set(schema, new MessageReader(parse(schema, { ros2: true })));
  return readers.get(schema);
}

function writer(schema) {
  return new MessageWriter(parse(schema, { ros2: true }));
}

/** Messages of one subscription, decoded, with their times (as strings: they are u64). */
function decoded(client, subscription, channel) {
  const read = reader(channel.schema);
  return client.inbox.message.items
    .filter((m) => m.subscriptionId === subscription)
    .map((m) => ({
      timestamp: m.timestamp.toString(),
      message: read.readMessage(m.data),
      trailing: read.lastReadHadTrailingBytes(),
      bytes: m.data.byteLength,
    }));
}

const sleep = (ms) => new Promise((resolve) => setTimeout(resolve, ms));

function hex(bytes, n) {
  return Buffer.from(bytes.buffer, bytes.byteOffset, Math.min(n, bytes.byteLength)).toString("hex");
}

const scenarios = {
  /** What the lab says when a client connects: server info, channels, services. */
  async connect(url) {
    const client = await connect(url, "viewer");
    const [info] = await client.inbox.serverInfo.count(1);
    const byTopic = await channels(client, ["/odom"]);
    const byName = await services(client, ["/lab/reset"]);
    const parsed = Object.values(byTopic).map((c) => {
      try {
        parse(c.schema, { ros2: true });
        return true;
      } catch (err) {
        return `${c.topic}: ${err}`;
      }
    });
    const observed = {
      protocol: client.ws.protocol,
      info,
      channels: Object.values(byTopic).map(({ schema, ...rest }) => ({
        ...rest,
        schemaLines: schema.split("\n").length,
      })),
      parsed,
      services: Object.values(byName).map((s) => ({
        name: s.name,
        type: s.type,
        request: s.request && { ...s.request, schema: undefined },
        response: s.response && { ...s.response, schema: undefined },
      })),
    };
    closeAll();
    return observed;
  },

  /** /odom subscribed, decoded with Foxglove's ROS 2 reader, beside the time frames. */
  async odom(url) {
    const client = await connect(url, "viewer");
    const byTopic = await channels(client, ["/odom"]);
    const odom = byTopic["/odom"];
    const sub = client.subscribe(odom.id);
    await client.inbox.message.until("5 /odom messages", (items) =>
      items.filter((m) => m.subscriptionId === sub).length >= 5,
    );
    const observed = {
      channel: { ...odom, schema: undefined },
      messages: decoded(client, sub, odom).slice(0, 5),
      times: client.inbox.time.items.map((t) => t.timestamp.toString()),
    };
    closeAll();
    return observed;
  },

  /** Client publishing: /cmd_vel in CDR then JSON turns the robot; a second client is refused. */
  async drive(url) {
    const driver = await connect(url, "driver");
    const byTopic = await channels(driver, ["/odom", "/cmd_vel", "/lab/driver"]);
    const odom = byTopic["/odom"];
    const odomSub = driver.subscribe(odom.id);
    const driverSub = driver.subscribe(byTopic["/lab/driver"].id);
    const twist = byTopic["/cmd_vel"];
    const cdr = driver.advertise({
      topic: "/cmd_vel", encoding: "cdr", schemaName: "geometry_msgs/msg/Twist",
      schema: twist.schema, schemaEncoding: "ros2msg",
    });
    const write = writer(twist.schema);
    const turn = { linear: { x: 0, y: 0, z: 0 }, angular: { x: 0, y: 0, z: 1.0 } };
    const turning = () =>
      decoded(driver, odomSub, odom).some((m) => m.message.twist.twist.angular.z > 0.2);
    for (let i = 0; i < 40 && !turning(); i += 1) {
      driver.sendMessage(cdr, write.writeMessage(turn));
      await sleep(100);
    }
    const turned = turning();
    const json = driver.advertise({
      topic: "/cmd_vel", encoding: "json", schemaName: "geometry_msgs/Twist",
    });
    const forward = { linear: { x: 0.3 }, angular: { z: 0 } };
    const moving = () =>
      decoded(driver, odomSub, odom).some((m) => m.message.twist.twist.linear.x > 0.1);
    for (let i = 0; i < 40 && !moving(); i += 1) {
      driver.sendMessage(json, new TextEncoder().encode(JSON.stringify(forward)));
      await sleep(100);
    }
    const moved = moving();
    for (let i = 0; i < 20; i += 1) { // long enough to be filed (the lab's least is 20 ticks)
      driver.sendMessage(json, new TextEncoder().encode(JSON.stringify(forward)));
      await sleep(100);
    }
    // Someone else tries to drive: refused, told why in a status; the robot is not theirs.
    const other = await connect(url, "other");
    await channels(other, ["/cmd_vel"]);
    const theirs = other.advertise({
      topic: "/cmd_vel", encoding: "json", schemaName: "geometry_msgs/msg/Twist",
    });
    other.sendMessage(theirs, new TextEncoder().encode(JSON.stringify(turn)));
    const [refused] = await other.inbox.status.count(1);
    const drivers = decoded(driver, driverSub, byTopic["/lab/driver"]).map((m) => m.message);
    const observed = {
      turned,
      moved,
      refused,
      driverStatuses: driver.inbox.status.items,
      drivers,
    };
    closeAll();
    await sleep(200);
    return observed;
  },

  /** Services: /lab/reset called in CDR and in JSON, /rosapi/topics, and a service that is not. */
  async services(url) {
    const client = await connect(url, "caller");
    const byName = await services(client, ["/lab/reset", "/rosapi/topics"]);
    const reset = byName["/lab/reset"];
    const request = writer(reset.request.schema).writeMessage({});
    client.sendServiceCallRequest({
      serviceId: reset.id, callId: 1, encoding: "cdr", data: request,
    });
    client.sendServiceCallRequest({
      serviceId: reset.id, callId: 2, encoding: "json", data: new TextEncoder().encode("{}"),
    });
    const topics = byName["/rosapi/topics"];
    client.sendServiceCallRequest({
      serviceId: topics.id, callId: 3, encoding: "json", data: new Uint8Array(),
    });
    client.sendServiceCallRequest({
      serviceId: 9999, callId: 4, encoding: "cdr", data: request,
    });
    client.sendServiceCallRequest({
      serviceId: reset.id, callId: 5, encoding: "cdr", data: new Uint8Array([1, 2]),
    });
    const answers = await client.inbox.serviceCallResponse.count(3);
    const failures = await client.inbox.serviceCallFailure.count(2);
    const byCall = Object.fromEntries(answers.map((a) => [a.callId, a]));
    const text = (a) => new TextDecoder().decode(a.data);
    const observed = {
      requestHex: hex(request, 16),
      cdr: {
        encoding: byCall[1].encoding,
        value: reader(reset.response.schema).readMessage(byCall[1].data),
      },
      json: { encoding: byCall[2].encoding, value: JSON.parse(text(byCall[2])) },
      topics: JSON.parse(text(byCall[3])),
      failures: failures.map(({ callId, serviceId, message }) => ({ callId, serviceId, message })),
    };
    closeAll();
    return observed;
  },

  /** The robot's parameters, read; setting one is refused and the values stay. */
  async params(url) {
    const client = await connect(url, "params");
    await client.inbox.serverInfo.count(1);
    client.getParameters([], "all");
    client.getParameters(["camera_width", "nope"], "some");
    client.setParameters([{ name: "camera_width", value: 1 }], "set");
    const values = await client.inbox.parameterValues.count(3);
    const [status] = await client.inbox.status.count(1);
    const observed = { values, status };
    closeAll();
    return observed;
  },

  /** The connection graph, and its update when this client subscribes. */
  async graph(url) {
    const client = await connect(url, "grapher");
    const byTopic = await channels(client, ["/odom"]);
    client.subscribeConnectionGraph();
    const [first] = await client.inbox.connectionGraphUpdate.count(1);
    client.subscribe(byTopic["/odom"].id);
    const updates = await client.inbox.connectionGraphUpdate.until(
      "an update with a subscriber of /odom",
      (items) => items.slice(1).some((u) => u.subscribedTopics.some((t) => t.name === "/odom")),
    );
    const observed = { first, later: updates.slice(1) };
    closeAll();
    return observed;
  },

  /** A robot that needs a key, given in the URL (FOXGLOVE_KEY): what comes, and the close. */
  async keyed(url) {
    const client = await connect(url, "keyed", { key: process.env.FOXGLOVE_KEY });
    await Promise.race([
      client.inbox.advertise.count(1).catch(() => {}),
      client.inbox.close.count(1).catch(() => {}),
    ]);
    await sleep(300); // anything that follows the first channels, or the close
    const [closed] = client.inbox.close.items;
    const observed = {
      channels: client.inbox.advertise.items.flat().length,
      statuses: client.inbox.status.items,
      closed: closed ? closed.code : null,
    };
    closeAll();
    return observed;
  },

  /** The camera: JPEG frames while subscribed, none once unsubscribed. */
  async camera(url) {
    const client = await connect(url, "camera");
    const topic = "/camera/image/compressed";
    const byTopic = await channels(client, [topic]);
    const channel = byTopic[topic];
    const sub = client.subscribe(channel.id);
    await client.inbox.message.until("3 camera frames", (items) =>
      items.filter((m) => m.subscriptionId === sub).length >= 3, 3 * WAIT_MS,
    );
    client.unsubscribe(sub);
    // A round trip: the lab handles a client's frames in order and sends in order, so once
    // this answer is here, any frame of the subscription still coming was sent before it.
    client.getParameters([], "after-unsubscribe");
    await client.inbox.parameterValues.until("the answer after unsubscribing", (items) =>
      items.some((v) => v.id === "after-unsubscribe"),
    );
    const before = client.inbox.message.items.length;
    await sleep(700);
    const frames = decoded(client, sub, channel).slice(0, 3);
    const observed = {
      frames: frames.map((f) => ({
        format: f.message.format,
        head: hex(f.message.data, 3),
        size: f.message.data.length,
        trailing: f.trailing,
      })),
      afterUnsubscribe: client.inbox.message.items.length - before,
    };
    closeAll();
    return observed;
  },
};

run(scenarios);
