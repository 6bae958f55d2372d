// Status frames: sent after Ros.setStatusLevel, never before, and naming the bad field.
// See harness.mjs for the contract.

import { Topic } from "roslib";

import { Inbox, connect, roundTrip, run } from "./harness.mjs";

run({
  // A asks for errors and publishes two messages with wrong field types and a good one, which
  // B hears; then B, which never asked for status, publishes a wrong field type too.
  async wrong_field_type(url) {
    const a = await connect(url, "A");
    const b = await connect(url, "B");
    const heard = new Inbox("/chatter at B");
    new Topic({ ros: b, name: "/chatter", messageType: "std_msgs/String" }).subscribe((msg) =>
      heard.push(msg),
    );
    await roundTrip(b);
    const routed = []; // what roslibjs emitted as "status:ID" events for A's publishes
    a.setStatusLevel("error");
    const chatter = new Topic({ ros: a, name: "/chatter", messageType: "std_msgs/String" });
    const cmd = new Topic({ ros: a, name: "/cmd_vel", messageType: "geometry_msgs/Twist" });
    // Topic.publish makes up each frame's id; note them on their way out (nothing changes).
    const publishIds = [];
    const originalCall = a.callOnConnection.bind(a);
    a.callOnConnection = (frame) => {
      if (frame.op === "publish") {
        publishIds.push(frame.id);
        a.once(`status:${frame.id}`, (status) => routed.push(status));
      }
      originalCall(frame);
    };
    chatter.publish({ data: 42 });
    cmd.publish({ linear: { x: "fast" } });
    chatter.publish({ data: "fine" });
    await a.statuses.count(2);
    await heard.count(1);
    await roundTrip(a); // any further status for those publishes would arrive before this

    const quiet = new Topic({ ros: b, name: "/chatter", messageType: "std_msgs/String" });
    quiet.publish({ data: 42 });
    await roundTrip(b);
    return {
      heard: heard.items,
      statuses: a.statuses.items,
      routed,
      publish_ids: publishIds,
      statuses_without_set_level: b.statuses.items,
    };
  },
});
