// pr2-table from the playground: raise the torso, tilt the head down at the table, open
// the right gripper, and say which objects the camera sees. Edit it, then "Run live" (the
// live robot, on the wall clock) or "Run as a trial" (committed, run sandboxed in
// lockstep and archived).
//
// A plain roslibjs program (npm roslib 2.x): it reaches the robot at LAB_BRIDGE_URL, in
// the page and in a trial alike. In a trial the robot waits for /lab/step (lockstep): the
// script publishes the tick's commands, calls /lab/step, and the answer comes once the
// tick's observations have been sent. Live, the robot runs on its own clock, so the script
// waits 100 ms a tick. Topics: docs/tasks.md.
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

const topic = (name, messageType) => new Topic({ ros, name, messageType });
const TRAJECTORY = "trajectory_msgs/msg/JointTrajectory";
/** Move `joints` to `positions` in `seconds` (a one-point trajectory). */
function move(name, joints, positions, seconds) {
  topic(name, TRAJECTORY).publish({
    joint_names: joints,
    points: [{ positions, time_from_start: { sec: Math.floor(seconds), nanosec: Math.round((seconds % 1) * 1e9) } }],
  });
}

let goal = null;
topic("/task/goal", "lab_msgs/msg/TableGoal").subscribe((m) => { goal = m; });
let seen = [];
topic("/objects", "lab_msgs/msg/DetectedObjectArray").subscribe((m) => { seen = m.objects.map((o) => o.name); });

console.log(lockstep ? "lockstep: a trial" : "live: on the robot's clock");
move("/torso/command", ["torso_lift_joint"], [0.2], 2.0);
move("/head/command", ["head_pan_joint", "head_tilt_joint"], [0, 0.7], 1.5);
topic("/right_gripper/command", "std_msgs/msg/Float64").publish({ data: 0.08 });

let ticks = 0;
let told = "";
while (await tick()) {
  ticks += 1;
  const now = seen.join(", ") || "nothing";
  if (now !== told) {
    console.log(`tick ${ticks}: the camera sees ${now}${goal ? ` (the goal: move ${goal.object})` : ""}`);
    told = now;
  }
  if (!lockstep && ticks >= 300) break; // live: 30 s, then the robot is free again
}
console.log(`done after ${ticks} ticks`);
ros.close();
