// Subscriptions with compression: cbor (binary frames, typed arrays) and png, decoded by
// roslibjs itself. See harness.mjs for the contract.

import { Topic } from "roslib";

import { Inbox, connect, roundTrip, run } from "./harness.mjs";

function listen(ros, name, messageType, compression) {
  const topic = new Topic({ ros, name, messageType, compression });
  const inbox = new Inbox(`${name} at ${ros.label}`);
  topic.subscribe((msg) => inbox.push(msg));
  return inbox;
}

/** How the frames for `topic` reached A's socket: "binary" or "text" (and png ops seen). */
function frameKinds(ros, topic) {
  const kinds = [];
  const socket = ros.transport.socket;
  socket.addEventListener("message", (event) => {
    if (typeof event.data === "string") {
      const frame = JSON.parse(event.data);
      if (frame.op === "png" || frame.topic === topic) kinds.push(`text:${frame.op}`);
    } else {
      kinds.push("binary");
    }
  });
  return kinds;
}

const JOINTS = {
  header: { stamp: { sec: 12, nanosec: 345 }, frame_id: "base_link" },
  name: ["shoulder", "elbow", "wrist"],
  position: [0.5, -1.25, 3.141592653589793],
  velocity: [0, 1e-9, -2.5e10],
};
const IMAGE = { height: 2, width: 3, encoding: "mono8", step: 3, data: [0, 1, 2, 127, 128, 255] };
const INTS = { data: [-2147483648, -1, 0, 7, 2147483647] };

run({
  // A subscribes with compression "cbor"; B publishes arrays of several element types.
  async cbor(url) {
    const a = await connect(url, "A");
    const b = await connect(url, "B");
    const kinds = frameKinds(a, "/joint_states");
    const joints = listen(a, "/joint_states", "sensor_msgs/msg/JointState", "cbor");
    const image = listen(a, "/camera/image", "sensor_msgs/Image", "cbor");
    const ints = listen(a, "/ints", "std_msgs/Int32MultiArray", "cbor");
    await roundTrip(a);
    new Topic({ ros: b, name: "/joint_states", messageType: "sensor_msgs/JointState" }).publish(
      JOINTS,
    );
    new Topic({ ros: b, name: "/camera/image", messageType: "sensor_msgs/Image" }).publish(IMAGE);
    new Topic({ ros: b, name: "/ints", messageType: "std_msgs/Int32MultiArray" }).publish(INTS);
    const [joint] = await joints.count(1);
    const [img] = await image.count(1);
    const [int] = await ints.count(1);
    return {
      sent: { joints: JOINTS, image: IMAGE, ints: INTS },
      joints: joint,
      image: img,
      ints: int,
      frames: kinds,
    };
  },

  // A subscribes with compression "cbor-raw": roslibjs hands over the CDR bytes untouched.
  async cbor_raw(url) {
    const a = await connect(url, "A");
    const b = await connect(url, "B");
    const chatter = listen(a, "/chatter", "std_msgs/String", "cbor-raw");
    const joints = listen(a, "/joint_states", "sensor_msgs/JointState", "cbor-raw");
    await roundTrip(a);
    new Topic({ ros: b, name: "/chatter", messageType: "std_msgs/String" }).publish({
      data: "raw hello",
    });
    new Topic({ ros: b, name: "/joint_states", messageType: "sensor_msgs/JointState" }).publish(
      JOINTS,
    );
    const [text] = await chatter.count(1);
    const [joint] = await joints.count(1);
    return { chatter: text, joints: joint };
  },

  // roslibjs' Topic has no fragment_size option, so A sends the subscribe frames itself
  // through Ros.callOnConnection; roslibjs reassembles the fragments (and then the png).
  async fragments(url) {
    const a = await connect(url, "A");
    const b = await connect(url, "B");
    const parts = [];
    a.transport.socket.addEventListener("message", (event) => {
      const frame = JSON.parse(event.data);
      if (frame.op !== "fragment") return;
      parts.push({ id: frame.id, num: frame.num, total: frame.total, size: frame.data.length });
    });
    const plain = new Inbox("/long at A");
    const packed = new Inbox("/long_png at A");
    a.on("/long", (frame) => plain.push(frame.msg));
    a.on("/long_png", (frame) => packed.push(frame.msg));
    const subscribe = { op: "subscribe", type: "std_msgs/String", fragment_size: 100 };
    a.callOnConnection({ ...subscribe, id: "frag-1", topic: "/long" });
    a.callOnConnection({ ...subscribe, id: "frag-2", topic: "/long_png", compression: "png" });
    await roundTrip(a);
    const text = Array.from({ length: 60 }, (_, i) => `part ${i};`).join(" ");
    for (const name of ["/long", "/long_png"]) {
      new Topic({ ros: b, name, messageType: "std_msgs/String" }).publish({ data: text });
    }
    await plain.count(1);
    await packed.count(1);
    return { sent: text, plain: plain.items, packed: packed.items, parts };
  },

  // A subscribes with compression "png"; B publishes text that needs UTF-8 and a long one.
  async png(url) {
    const a = await connect(url, "A");
    const b = await connect(url, "B");
    const kinds = frameKinds(a, "/chatter");
    const chatter = listen(a, "/chatter", "std_msgs/String", "png");
    const twist = listen(a, "/cmd_vel", "geometry_msgs/Twist", "png");
    await roundTrip(a);
    const say = new Topic({ ros: b, name: "/chatter", messageType: "std_msgs/String" });
    const texts = ["héllo wörld ✓ \"quoted\"\n", "x".repeat(5000)];
    for (const data of texts) say.publish({ data });
    new Topic({ ros: b, name: "/cmd_vel", messageType: "geometry_msgs/Twist" }).publish({
      linear: { x: 0.25 },
      angular: { z: 1 },
    });
    await chatter.count(2);
    await twist.count(1);
    return { sent: texts, chatter: chatter.items, twist: twist.items, frames: kinds };
  },
});
