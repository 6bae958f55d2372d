// The PR2's page (pr2-table): the robot and the table's objects in 3D (three.js, the
// scene graph of the task's model, as the record view draws it: scene.js), posed live
// from /joint_states, /tf and /objects, the head camera beside it, and controls for the
// base, the torso, the head, the grippers, and a Cartesian target per arm: drag it in
// the 3D view (TransformControls) or move it with the keyboard, and the arm follows
// (/left_arm/pose, /right_arm/pose: docs/tasks.md). Everything goes through the bridge;
// only the model's shapes come from the lab's HTTP server (/api/robots/NAME/scene).
// The commands' messages are made in arms.js.

import * as THREE from "three";
import { OrbitControls } from "three/addons/controls/OrbitControls.min.js";
import { TransformControls } from "three/addons/controls/TransformControls.min.js";
import { Topic } from "/static/vendor/roslib/roslib.min.js";
import { $, config, start } from "../page.js";
import { buildScene, frame, kinematics } from "../scene.js";
import {
  BASE_KEYS, READY, STEP, TARGET_KEYS, ZERO_TWIST, armJoints, baseTwist, readyPlan, targetEvent,
  targetPose, targetWords, trajectory,
} from "./arms.js";
import { camera, connect } from "./lab.js";
import { repeater } from "./messages.js";

const ARMS = {
  left: { topic: "/left_arm/pose", tool: "l_gripper_tool_frame", color: 0x2e9d4f },
  right: { topic: "/right_arm/pose", tool: "r_gripper_tool_frame", color: 0xd0452f },
};
const pose3 = (p, q) => ({ p: new THREE.Vector3(p.x, p.y, p.z), q: new THREE.Quaternion(q.x, q.y, q.z, q.w) });

async function main() {
  const live = await connect(config("live-config"));
  camera(live, $("camera"));
  const view = await sceneView(live);
  const arms = armTargets(live, view);
  window.labPr2 = {  // for scripts and tests: where things are, and moving a target
    seed: () => (view.loading ? null : view.info.seed),  // the episode whose scene is shown
    tool: (arm) => view.tools[ARMS[arm].tool]?.p.toArray() ?? null,
    target: (arm) => arms.targets[arm].inBase?.p.toArray() ?? null,
    bodyPose: (name) => (name in view.body
      ? [...view.scene.pos[view.body[name]].toArray(), ...view.scene.quat[view.body[name]].toArray()] : null),
  };
  follow(live.ros, view, arms);
  draw(view);
  baseControls(live, view, arms);
  jointControls(live, view, arms);
  document.body.dataset.ready = "yes";  // every handler is in place
}

/**
 * The 3D view: its renderer, camera and orbit, and the episode's model. Each episode has
 * its own model (the objects the seed drew), loaded again when the seed changes; ``q`` is
 * MuJoCo's qpos, kept from the robot's topics, and ``dirty`` says the scene needs posing.
 * ``onLoad`` are called with each new scene before it is shown.
 */
async function sceneView(live) {
  const holder = $("scene3d");
  const width = holder.clientWidth || 640, height = Math.round(width * 0.7);
  const renderer = new THREE.WebGLRenderer({ antialias: true });
  renderer.setPixelRatio(Math.min(2, window.devicePixelRatio || 1));
  renderer.setSize(width, height);
  renderer.domElement.id = "pr2-scene";
  holder.replaceChildren(renderer.domElement);
  const view = {
    renderer, info: null, scene: null, q: null, body: null, root: undefined, rest: null,
    worldFromOdom: null,
    worldFromBase: null,  // from /tf: odom -> base_footprint
    tools: {},  // the tool frames in base_footprint, from /tf
    dirty: true, loading: null, onLoad: [],
    toWorld: (p) => p.clone().applyQuaternion(view.worldFromBase.q).add(view.worldFromBase.p),
    toBase: (p) => p.clone().sub(view.worldFromBase.p).applyQuaternion(view.worldFromBase.q.clone().invert()),
  };
  const load = async () => {
    const info = view.info = await (await fetch(live.config.scene)).json();
    const next = await buildScene(THREE, info);
    for (const f of view.onLoad) f(next);
    view.scene = next;
    view.q = info.qpos.slice();
    view.body = Object.fromEntries(info.bodies.map((b, i) => [b.name, i]));
    view.root = view.body[info.root];
    view.rest = kinematics(THREE, info.bodies);  // where the root is at rest: its planar joints measure from there
    view.rest.forward(info.rest);
    const o = info.odom;
    view.worldFromOdom = pose3({ x: o[0], y: o[1], z: o[2] }, { x: o[3], y: o[4], z: o[5], w: o[6] });
    view.worldFromBase = null;
    view.scene.pose(view.q);
    view.dirty = true;
  };
  await load();
  const reload = (seed) => {  // once per seed; a seed that came during a load is loaded after
    if (seed === view.info.seed || view.loading) return;
    view.loading = load().finally(() => {
      view.loading = null;
      if (live.episode) reload(live.episode.seed);
    });
  };
  live.onEpisode.push((m) => reload(m.seed));

  const { scene } = view;
  scene.pose(view.q);
  scene.world.updateMatrixWorld(true);
  const { camera: eye, centre } = frame(THREE, scene.solids.filter((m) => m.parent !== scene.world), [-0.9, -0.7, 0.55], width / height);
  view.eye = eye;
  view.orbit = new OrbitControls(eye, renderer.domElement);
  view.orbit.target.copy(centre);
  view.orbit.update();
  return view;
}

/** Draw the view each animation frame while the page is in view, posed when dirty. */
function draw(view) {
  let frames = 0;
  const next = () => {
    requestAnimationFrame(next);
    if (document.visibilityState === "hidden") return;
    if (view.dirty) { view.scene.pose(view.q); view.dirty = false; }
    view.renderer.render(view.scene.world, view.eye);
    frames += 1;
    view.renderer.domElement.dataset.frames = String(frames);
  };
  requestAnimationFrame(next);
}

/**
 * The Cartesian targets, one per arm: a sphere in the scene, in base_footprint once the
 * tool's frame is known (a target starts where the tool is, pointing as it points), and
 * the handle (TransformControls) on the selected one. Moving a target sends it.
 */
function armTargets(live, view) {
  const targets = {};
  for (const [arm, spec] of Object.entries(ARMS)) {
    const mesh = new THREE.Mesh(new THREE.SphereGeometry(0.025, 16, 12),
      new THREE.MeshLambertMaterial({ color: spec.color, transparent: true, opacity: 0.8 }));
    mesh.add(new THREE.AxesHelper(0.08));
    mesh.visible = false;
    mesh.name = `${arm}-target`;
    view.scene.world.add(mesh);
    targets[arm] = { mesh, inBase: null, send: live.command(spec.topic, "geometry_msgs/msg/PoseStamped") };
  }
  const handle = new TransformControls(view.eye, view.renderer.domElement);
  handle.setSize(0.8);
  view.scene.world.add(handle.getHelper());
  handle.addEventListener("dragging-changed", (e) => { view.orbit.enabled = !e.value; });
  view.onLoad.push((next) => {  // a new episode's scene: the targets start again
    for (const t of Object.values(targets)) { next.world.add(t.mesh); t.inBase = null; t.mesh.visible = false; }
    next.world.add(handle.getHelper());
  });
  const arms = { targets, handle, selected: "left" };
  arms.place = (arm) => {
    const t = targets[arm];
    if (!t.inBase || !view.worldFromBase) return;
    t.mesh.position.copy(view.toWorld(t.inBase.p));
    t.mesh.quaternion.copy(view.worldFromBase.q).multiply(t.inBase.q);
    t.mesh.visible = true;
  };
  let lastSent = 0;
  arms.send = (arm) => {
    const { p, q } = targets[arm].inBase;
    targets[arm].send(targetPose(p, q));
    $(`${arm}-target-at`).textContent = targetWords(p);
    live.ux("target", arm, targetEvent(p));
  };
  arms.grab = (arm) => {  // a target starts where the tool is, pointing as it points
    const t = targets[arm], tool = view.tools[ARMS[arm].tool];
    if (!t.inBase && tool) {
      t.inBase = { p: tool.p.clone(), q: tool.q.clone() };
      arms.place(arm);
    }
    return t.inBase !== null;
  };
  arms.select = (arm) => {
    arms.selected = arm;
    for (const b of document.querySelectorAll("input[name=arm]")) b.checked = b.value === arm;
    if (arms.grab(arm)) handle.attach(targets[arm].mesh);
  };
  for (const b of document.querySelectorAll("input[name=arm]")) b.addEventListener("change", () => arms.select(b.value));
  handle.addEventListener("objectChange", () => {
    const t = targets[arms.selected];
    if (!view.worldFromBase || !t.inBase) return;
    t.inBase.p.copy(view.toBase(t.mesh.position));
    const now = performance.now();
    if (now - lastSent > 100) { lastSent = now; arms.send(arms.selected); }
  });
  handle.addEventListener("mouseUp", () => targets[arms.selected].inBase && arms.send(arms.selected));
  return arms;
}

/** The robot's topics pose the scene: /joint_states the joints, /tf the base in odom and
 * the tools in the base, /objects the table's objects. */
function follow(ros, view, arms) {
  new Topic({ ros, name: "/joint_states", messageType: "sensor_msgs/msg/JointState" }).subscribe((m) => {
    m.name.forEach((name, i) => { if (name in view.info.joints) view.q[view.info.joints[name]] = m.position[i]; });
    view.dirty = true;
  });
  new Topic({ ros, name: "/tf", messageType: "tf2_msgs/msg/TFMessage" }).subscribe((m) => {
    for (const t of m.transforms) {
      const local = pose3(t.transform.translation, t.transform.rotation);
      if (t.header.frame_id === "odom" && t.child_frame_id === view.info.root) {
        const odom = view.worldFromOdom;
        view.worldFromBase = { p: local.p.clone().applyQuaternion(odom.q).add(odom.p), q: odom.q.clone().multiply(local.q) };
        placeRoot(view, view.worldFromBase);
      } else if (t.header.frame_id === view.info.root) {
        view.tools[t.child_frame_id] = local;
      }
    }
    for (const arm of Object.keys(ARMS)) arms.place(arm);
    if (!arms.targets[arms.selected].inBase && arms.grab(arms.selected)) arms.handle.attach(arms.targets[arms.selected].mesh);
    view.dirty = true;
  });
  new Topic({ ros, name: "/objects", messageType: "lab_msgs/msg/DetectedObjectArray", throttle_rate: 100 }).subscribe((m) => {
    if (!view.worldFromBase) return;
    for (const o of m.objects) {
      const i = view.body[o.name];
      const free = i === undefined ? null : view.info.bodies[i].joints.find((j) => j[0] === 0);
      if (!free) continue;
      const local = pose3(o.pose.position, o.pose.orientation);
      const p = view.toWorld(local.p), r = view.worldFromBase.q.clone().multiply(local.q);
      view.q.splice(free[1], 7, p.x, p.y, p.z, r.w, r.x, r.y, r.z);
    }
    view.dirty = true;
  });
}

/** The base's planar joints in ``view.q``, so that it is at ``pose`` in the world. */
function placeRoot(view, pose) {
  const { root, rest, info, q } = view;
  if (root === undefined) return;
  const yaw = (o) => new THREE.Euler().setFromQuaternion(o, "ZYX").z;
  const turn = yaw(pose.q) - yaw(rest.quat[root]);
  for (const [type, adr, ax, ay, az, , , , ref] of info.bodies[root].joints) {
    if (type === 3) q[adr] = ref + Math.atan2(Math.sin(turn), Math.cos(turn)) * (Math.sign(az) || 1);
    else if (type === 2) q[adr] = ref + pose.p.clone().sub(rest.pos[root]).dot(new THREE.Vector3(ax, ay, az));
  }
}

/** The keyboard and the on-screen pad: the base while a key is held (W A S D Q E), the
 * arm to move (1, 2) and its target (I K J L U O, a step a press). */
function baseControls(live, view, arms) {
  const base = repeater(live.command("/base/cmd_vel", "geometry_msgs/msg/Twist"), ZERO_TWIST);
  const held = new Set();
  const moveBase = () => base.set(baseTwist(held));
  document.addEventListener("keydown", (e) => {
    if (e.target.closest("input[type=number], textarea")) return;
    const k = e.key.toLowerCase();
    if (k in BASE_KEYS) { held.add(k); moveBase(); e.preventDefault(); return; }
    if (k === "1" || k === "2") { arms.select(k === "1" ? "left" : "right"); return; }
    if (k in TARGET_KEYS && arms.grab(arms.selected)) {
      arms.targets[arms.selected].inBase.p.add(new THREE.Vector3(...TARGET_KEYS[k]).multiplyScalar(STEP));
      arms.place(arms.selected);
      arms.send(arms.selected);
      view.dirty = true;
      e.preventDefault();
    }
  });
  document.addEventListener("keyup", (e) => { if (held.delete(e.key.toLowerCase())) moveBase(); });
  window.addEventListener("blur", () => { held.clear(); moveBase(); });
  for (const button of document.querySelectorAll("#base-pad button[data-key]")) {
    const k = button.dataset.key;
    button.addEventListener("pointerdown", () => { held.add(k); moveBase(); });
    for (const end of ["pointerup", "pointercancel", "pointerleave"]) {
      button.addEventListener(end, () => { if (held.delete(k)) moveBase(); });
    }
  }
}

/** The torso, the head and the grippers from their inputs, and the arms' ready pose. */
function jointControls(live, view, arms) {
  const command = (topic) => {
    const send = live.command(topic, "trajectory_msgs/msg/JointTrajectory");
    return (names, points) => send(trajectory(names, points));
  };
  const torso = command("/torso/command"), head = command("/head/command");
  $("torso").addEventListener("change", (e) => torso(["torso_lift_joint"], [[Number(e.target.value), 0]]));
  const aim = () => head(["head_pan_joint", "head_tilt_joint"], [[[Number($("pan").value), Number($("tilt").value)], 0]]);
  $("pan").addEventListener("change", aim);
  $("tilt").addEventListener("change", aim);
  for (const side of ["left", "right"]) {
    const send = live.command(`/${side}_gripper/command`, "std_msgs/msg/Float64");
    $(`${side}-gripper`).addEventListener("change", (e) => send({ data: Number(e.target.value) }));
  }
  const armCommands = { left: command("/left_arm/command"), right: command("/right_arm/command") };
  $("ready").addEventListener("click", () => {  // untuck without sweeping the table
    torso(["torso_lift_joint"], [[0.2, 4]]);
    $("torso").value = "0.2";
    setTimeout(() => {
      for (const [side, ready] of Object.entries(READY)) {
        const names = armJoints(side);
        armCommands[side](names, readyPlan(names.map((n) => view.q[view.info.joints[n]]), ready));
      }
    }, 4000);
    setTimeout(() => {  // the targets start again from where the tools are now
      for (const arm of Object.keys(ARMS)) { arms.targets[arm].inBase = null; arms.grab(arm); }
    }, 9500);
  });
}

start(main);
