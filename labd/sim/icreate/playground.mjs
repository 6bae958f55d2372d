// icreate-maze from the playground: drive ahead; when a bumper touches a wall, back off
// and turn away, and log what happens. Edit it, then "Run live" (the live robot, on the
// wall clock) or "Run as a trial" (committed, run sandboxed in lockstep and archived).
//
// A plain roslibjs program (npm roslib 2.x): it reaches the robot at LAB_BRIDGE_URL, in
// the page and in a trial alike. In a trial the robot waits for /lab/step (lockstep): the
// script publishes the tick's command, calls /lab/step, and the answer comes once the
// tick's observations have been sent. Live, the robot runs on its own clock, so the script
// sends a command every 100 ms. Topics: docs/tasks.md.
import { Ros, Service, Topic } from "roslib";

const ros = new Ros({});
const connected = new Promise((resolve, reject) => {
  ros.once("connection", resolve);
  ros.once("error", () => reject(new Error("cannot reach the robot")));
});
await ros.connect(process.env.LAB_BRIDGE_URL ?? "ws://127.0.0.1:9090");
await connected;

// A lockstep robot (a trial) offers /lab/step; a live one runs on the wall clock.
const services = await new Promise((resolve, reject) => ros.getServices(resolve, reject));
const lockstep = services.includes("/lab/step");
const step = new Service({ ros, name: "/lab/step", serviceType: "std_srvs/srv/Trigger" });

/** One control tick: true while the episode runs. */
function tick() {
  if (!lockstep) return new Promise((resolve) => setTimeout(() => resolve(true), 100));
  return new Promise((resolve, reject) => {
    step.callService({}, (answer) => resolve(answer.success && answer.message.endsWith(": running")), reject);
  });
}

let bumper = { left: false, right: false };
new Topic({ ros, name: "/bumper", messageType: "lab_msgs/msg/Bumper" }).subscribe((m) => { bumper = m; });
let episode = null;
new Topic({ ros, name: "/lab/episode", messageType: "lab_msgs/msg/Episode" }).subscribe((m) => { episode = m; });
const cmdVel = new Topic({ ros, name: "/cmd_vel", messageType: "geometry_msgs/msg/Twist" });

function drive(speed, turn) {
  cmdVel.publish({ linear: { x: speed, y: 0, z: 0 }, angular: { x: 0, y: 0, z: turn } });
}

console.log(lockstep ? "lockstep: a trial" : "live: on the robot's clock");
let backing = 0; // ticks left backing off and turning
let turn = 1.5;  // rad/s, the way it turns away
let bumps = 0;
for (;;) {
  if (backing === 0 && (bumper.left || bumper.right)) {
    bumps += 1;
    turn = bumper.left ? -1.5 : 1.5; // away from the side that touched
    backing = 15;
    console.log(`bump ${bumps} (${bumper.left ? "left" : ""}${bumper.right ? " right" : ""}): turning away`);
  }
  if (backing > 0) {
    backing -= 1;
    drive(backing > 8 ? -0.15 : 0, backing > 8 ? 0 : turn);
  } else {
    drive(0.3, 0);
  }
  if (!(await tick())) break;
}
console.log(`episode over: ${episode?.status} ${episode?.reason ?? ""}`);
ros.close();
