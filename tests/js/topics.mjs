// Topics through the bridge between separate roslibjs connections: publish and subscribe,
// defaults, latching, throttling and unsubscribing. See harness.mjs for the contract.

import { Topic } from "roslib";

import { Inbox, connect, roundTrip, run } from "./harness.mjs";

function listen(ros, name, messageType, options = {}) {
  const topic = new Topic({ ros, name, messageType, ...options });
  const inbox = new Inbox(`${name} at ${ros.label}`);
  topic.subscribe((msg) => inbox.push(msg));
  return { topic, inbox };
}

/** Frames the bridge sent this connection that publish on `topic` (whoever listens). */
function wire(ros, topic) {
  const inbox = new Inbox(`publish frames of ${topic}`);
  ros.transport.on("message", (frame) => {
    if (frame.op === "publish" && frame.topic === topic) inbox.push(frame.msg);
  });
  return inbox;
}

run({
  // A listens to /chatter and /cmd_vel and echoes /chatter on /chatter_echo; B publishes
  // and listens to the echo: both connections publish and subscribe.
  async pubsub(url) {
    const a = await connect(url, "A");
    const b = await connect(url, "B");
    const chatter = listen(a, "/chatter", "std_msgs/String");
    const twist = listen(a, "/cmd_vel", "geometry_msgs/Twist");
    const echo = new Topic({ ros: a, name: "/chatter_echo", messageType: "std_msgs/msg/String" });
    chatter.topic.subscribe((msg) => echo.publish({ data: `echo: ${msg.data}` }));
    const echoed = listen(b, "/chatter_echo", "std_msgs/String");
    await roundTrip(a);
    await roundTrip(b);

    const say = new Topic({ ros: b, name: "/chatter", messageType: "std_msgs/msg/String" });
    const drive = new Topic({ ros: b, name: "/cmd_vel", messageType: "geometry_msgs/msg/Twist" });
    for (const text of ["one", "two", "three"]) say.publish({ data: text });
    drive.publish({ linear: { x: 1.5 }, angular: { z: -0.25 } });

    await chatter.inbox.count(3);
    await twist.inbox.count(1);
    await echoed.inbox.count(3);
    return { chatter: chatter.inbox.items, twist: twist.inbox.items, echoed: echoed.inbox.items };
  },

  // B publishes once on a latched topic; A subscribes afterwards and still gets it.
  async latched(url) {
    const b = await connect(url, "B");
    const map = new Topic({
      ros: b,
      name: "/map_name",
      messageType: "std_msgs/String",
      latch: true,
    });
    map.publish({ data: "maze-7" });
    await roundTrip(b);
    const a = await connect(url, "A");
    const late = listen(a, "/map_name", "std_msgs/String");
    await late.inbox.count(1);
    await roundTrip(a);
    return { received: late.inbox.items };
  },

  // A subscribes with throttle_rate 1000 ms, C without; B publishes ten messages at once.
  async throttle(url) {
    const a = await connect(url, "A");
    const c = await connect(url, "C");
    const b = await connect(url, "B");
    const slow = listen(a, "/burst", "std_msgs/String", { throttle_rate: 1000 });
    const fast = listen(c, "/burst", "std_msgs/String");
    await roundTrip(a);
    await roundTrip(c);
    const burst = new Topic({ ros: b, name: "/burst", messageType: "std_msgs/String" });
    const start = performance.now();
    for (let i = 0; i < 10; i++) burst.publish({ data: String(i) });
    await fast.inbox.count(10);
    const burstMs = fast.inbox.times[9] - start;
    await slow.inbox.until('"9"', (items) => items.some((m) => m.data === "9"));
    await roundTrip(a); // anything else the bridge still held for A arrives before this
    return {
      throttled: slow.inbox.items.map((m) => m.data),
      throttled_gaps_ms: slow.inbox.times.slice(1).map((t, i) => t - slow.inbox.times[i]),
      unthrottled: fast.inbox.items.map((m) => m.data),
      burst_ms: burstMs,
    };
  },

  // A has two Topic objects on /chatter (say, two widgets on one page). Each callback sees
  // each message once; unsubscribing one leaves the other subscribed.
  async two_topic_objects(url) {
    const a = await connect(url, "A");
    const b = await connect(url, "B");
    const frames = wire(a, "/chatter");
    const first = listen(a, "/chatter", "std_msgs/String");
    const second = listen(a, "/chatter", "std_msgs/String");
    await roundTrip(a);
    const say = new Topic({ ros: b, name: "/chatter", messageType: "std_msgs/String" });
    say.publish({ data: "x" });
    say.publish({ data: "y" });
    await first.inbox.count(2);
    await second.inbox.count(2);
    first.topic.unsubscribe();
    await roundTrip(a);
    say.publish({ data: "z" });
    await second.inbox.count(3);
    await roundTrip(b);
    await roundTrip(a);
    return {
      first: first.inbox.items.map((m) => m.data),
      second: second.inbox.items.map((m) => m.data),
      on_the_wire: frames.items.map((m) => m.data),
    };
  },

  // A unsubscribes; a later publish must not even reach A's socket.
  async unsubscribe(url) {
    const a = await connect(url, "A");
    const b = await connect(url, "B");
    const frames = wire(a, "/chatter");
    const sub = listen(a, "/chatter", "std_msgs/String");
    await roundTrip(a);
    const say = new Topic({ ros: b, name: "/chatter", messageType: "std_msgs/String" });
    say.publish({ data: "before" });
    await sub.inbox.count(1);
    sub.topic.unsubscribe();
    await roundTrip(a);
    say.publish({ data: "after" });
    await roundTrip(b); // the publish is handled, so anything for A is queued for A...
    await roundTrip(a); // ...and has arrived before this answer
    return { callback: sub.inbox.items, on_the_wire: frames.items };
  },
});
