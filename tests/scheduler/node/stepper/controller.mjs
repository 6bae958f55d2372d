// A JavaScript controller in lockstep: drive in a slow arc, step until the episode ends.
// The trials' tests run it as is, and with a package of its own (ms, from its lock file).
import { Ros, Service, Topic } from "roslib";

const mode = process.argv[2] ?? "step";
const ros = new Ros({ url: process.env.LAB_BRIDGE_URL ?? "ws://127.0.0.1:9090" });
await new Promise((resolve, reject) => {
  ros.on("connection", resolve);
  ros.on("error", (err) => reject(new Error(`cannot reach the lab: ${err?.message ?? err}`)));
});
if (mode === "package") {
  const { default: ms } = await import("ms");
  console.error(`ms("2 minutes") is ${ms("2 minutes")}`);
}
const cmd = new Topic({ ros, name: "/cmd_vel", messageType: "geometry_msgs/msg/Twist" });
const step = new Service({ ros, name: "/lab/step", serviceType: "std_srvs/srv/Trigger" });
const call = () =>
  new Promise((resolve, reject) => step.callService({}, resolve, (err) => reject(new Error(err))));
let ticks = 0;
for (;;) {
  cmd.publish({ linear: { x: 0.2 }, angular: { z: 0.3 } });
  const answer = await call();
  if (!answer.success) {
    console.error(`the episode ended after ${ticks} ticks: ${answer.message}`);
    break;
  }
  ticks += 1;
  if (mode === "crash" && ticks === 3) {
    throw new Error("the controller broke on purpose");
  }
  if (mode === "hang" && ticks === 3) {
    await new Promise(() => setInterval(() => {}, 1000));
  }
}
ros.close();
