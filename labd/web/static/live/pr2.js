// The PR2's page (pr2-table): the robot and the table's objects in 3D (three.js, the
// scene graph of the task's model, as the record view draws it: scene.js), posed live
// from /joint_states, /tf and /objects, the head camera beside it, and controls for the
// base, the torso, the head, the grippers, and a Cartesian target per arm: drag it in
// the 3D view (TransformControls) or move it with the keyboard, and the arm follows
// (/left_arm/pose, /right_arm/pose: docs/tasks.md). Everything goes through the bridge;
// only the model's shapes come from the lab's HTTP server (/api/robots/NAME/scene).

import * as THREE from "three";
import { OrbitControls } from "three/addons/controls/OrbitControls.min.js";
import { TransformControls } from "three/addons/controls/TransformControls.min.js";
import { Topic } from "/static/vendor/roslib/roslib.min.js";
import { buildScene, frame, kinematics } from "/static/scene.js";
import { camera, config, connect, repeater } from "/static/live/lab.js";

const $ = (id) => document.getElementById(id);
const ARMS = {
  left: { topic: "/left_arm/pose", tool: "l_gripper_tool_frame", color: 0x2e9d4f },
  right: { topic: "/right_arm/pose", tool: "r_gripper_tool_frame", color: 0xd0452f },
};
const STEP = 0.02;  // m per key press of a target
const TARGET_KEYS = { i: [1, 0, 0], k: [-1, 0, 0], j: [0, 1, 0], l: [0, -1, 0], u: [0, 0, 1], o: [0, 0, -1] };
const BASE_KEYS = { w: [1, 0, 0], s: [-1, 0, 0], a: [0, 1, 0], d: [0, -1, 0], q: [0, 0, 1], e: [0, 0, -1] };
const READY = {  // the arms' ready pose and the joints' names (docs/tasks.md)
  left: [0.66, -0.18, 1.34, -1.65, 1.37, -1.78, 2.1],
  right: [-0.66, -0.18, -1.34, -1.65, -1.37, -1.78, 1.04],
};
const JOINTS = ["shoulder_pan", "shoulder_lift", "upper_arm_roll", "elbow_flex", "forearm_roll", "wrist_flex", "wrist_roll"];
const pose3 = (p, q) => ({ p: new THREE.Vector3(p.x, p.y, p.z), q: new THREE.Quaternion(q.x, q.y, q.z, q.w) });

async function main() {
  const cfg = config();
  const live = await connect(cfg);
  const { ros } = live;
  camera(live, $("camera"));

  // -- the scene -------------------------------------------------------------------------
  const holder = $("scene3d");
  const width = holder.clientWidth || 640, height = Math.round(width * 0.7);
  const renderer = new THREE.WebGLRenderer({ antialias: true });
  renderer.setPixelRatio(Math.min(2, window.devicePixelRatio || 1));
  renderer.setSize(width, height);
  renderer.domElement.id = "pr2-scene";
  holder.replaceChildren(renderer.domElement);
  // Each episode has its own model (the objects the seed drew): loaded again when the
  // seed changes. ``q`` is MuJoCo's qpos, kept from the robot's topics.
  let info, scene, q, body, root, rest, worldFromOdom;
  let worldFromBase = null;  // from /tf: odom -> base_footprint
  const tools = {};  // the tool frames in base_footprint, from /tf
  const targets = {};
  let handle = null, dirty = true;
  const load = async () => {
    info = await (await fetch(cfg.scene)).json();
    const next = await buildScene(THREE, info);
    for (const t of Object.values(targets)) { next.world.add(t.mesh); t.inBase = null; t.mesh.visible = false; }
    if (handle) next.world.add(handle.getHelper());
    scene = next;
    q = info.qpos.slice();
    body = Object.fromEntries(info.bodies.map((b, i) => [b.name, i]));
    root = body[info.root];
    rest = kinematics(THREE, info.bodies);  // where the root is at rest: its planar joints measure from there
    rest.forward(info.rest);
    worldFromOdom = pose3({ x: info.odom[0], y: info.odom[1], z: info.odom[2] },
      { x: info.odom[3], y: info.odom[4], z: info.odom[5], w: info.odom[6] });
    worldFromBase = null;
    scene.pose(q);
    dirty = true;
  };
  await load();
  let loading = null;
  const reload = (seed) => {  // once per seed; a seed that came during a load is loaded after
    if (seed === info.seed || loading) return;
    loading = load().finally(() => {
      loading = null;
      if (live.episode) reload(live.episode.seed);
    });
  };
  live.onEpisode.push((m) => reload(m.seed));

  scene.pose(q);
  scene.world.updateMatrixWorld(true);
  const { camera: eye, centre } = frame(THREE, scene.solids.filter((m) => m.parent !== scene.world), [-0.9, -0.7, 0.55], width / height);
  const orbit = new OrbitControls(eye, renderer.domElement);
  orbit.target.copy(centre);
  orbit.update();

  // -- Cartesian targets, one per arm -------------------------------------------------------
  for (const [arm, spec] of Object.entries(ARMS)) {
    const mesh = new THREE.Mesh(new THREE.SphereGeometry(0.025, 16, 12),
      new THREE.MeshLambertMaterial({ color: spec.color, transparent: true, opacity: 0.8 }));
    mesh.add(new THREE.AxesHelper(0.08));
    mesh.visible = false;
    mesh.name = `${arm}-target`;
    scene.world.add(mesh);
    targets[arm] = { mesh, inBase: null, send: live.command(spec.topic, "geometry_msgs/msg/PoseStamped") };
  }
  let selected = "left";
  handle = new TransformControls(eye, renderer.domElement);
  handle.setSize(0.8);
  scene.world.add(handle.getHelper());
  handle.addEventListener("dragging-changed", (e) => { orbit.enabled = !e.value; });
  const toWorld = (p) => p.clone().applyQuaternion(worldFromBase.q).add(worldFromBase.p);
  const toBase = (p) => p.clone().sub(worldFromBase.p).applyQuaternion(worldFromBase.q.clone().invert());
  const place = (arm) => {
    const t = targets[arm];
    if (!t.inBase || !worldFromBase) return;
    t.mesh.position.copy(toWorld(t.inBase.p));
    t.mesh.quaternion.copy(worldFromBase.q).multiply(t.inBase.q);
    t.mesh.visible = true;
  };
  let lastSent = 0;
  const sendTarget = (arm) => {
    const t = targets[arm];
    const p = t.inBase.p, o = t.inBase.q;
    t.send({ header: { stamp: { sec: 0, nanosec: 0 }, frame_id: "base_footprint" },
             pose: { position: { x: p.x, y: p.y, z: p.z }, orientation: { x: o.x, y: o.y, z: o.z, w: o.w } } });
    $(`${arm}-target-at`).textContent = `(${p.x.toFixed(2)}, ${p.y.toFixed(2)}, ${p.z.toFixed(2)}) m`;
    live.ux("target", arm, { x: +p.x.toFixed(3), y: +p.y.toFixed(3), z: +p.z.toFixed(3) });
  };
  const grab = (arm) => {  // a target starts where the tool is, pointing as it points
    const t = targets[arm];
    if (!t.inBase && tools[ARMS[arm].tool]) {
      const tool = tools[ARMS[arm].tool];
      t.inBase = { p: tool.p.clone(), q: tool.q.clone() };
      place(arm);
    }
    return t.inBase !== null;
  };
  const select = (arm) => {
    selected = arm;
    for (const b of document.querySelectorAll("input[name=arm]")) b.checked = b.value === arm;
    if (grab(arm)) handle.attach(targets[arm].mesh);
  };
  for (const b of document.querySelectorAll("input[name=arm]")) b.addEventListener("change", () => select(b.value));
  handle.addEventListener("objectChange", () => {
    const t = targets[selected];
    if (!worldFromBase || !t.inBase) return;
    t.inBase.p.copy(toBase(t.mesh.position));
    const now = performance.now();
    if (now - lastSent > 100) { lastSent = now; sendTarget(selected); }
  });
  handle.addEventListener("mouseUp", () => targets[selected].inBase && sendTarget(selected));
  window.labPr2 = {  // for scripts and tests: where things are, and moving a target
    seed: () => (loading ? null : info.seed),  // the episode whose scene is shown
    tool: (arm) => tools[ARMS[arm].tool]?.p.toArray() ?? null,
    target: (arm) => targets[arm].inBase?.p.toArray() ?? null,
    bodyPose: (name) => (name in body ? [...scene.pos[body[name]].toArray(), ...scene.quat[body[name]].toArray()] : null),
  };

  // -- the robot's topics pose the scene -----------------------------------------------------
  new Topic({ ros, name: "/joint_states", messageType: "sensor_msgs/msg/JointState" }).subscribe((m) => {
    m.name.forEach((name, i) => { if (name in info.joints) q[info.joints[name]] = m.position[i]; });
    dirty = true;
  });
  new Topic({ ros, name: "/tf", messageType: "tf2_msgs/msg/TFMessage" }).subscribe((m) => {
    for (const t of m.transforms) {
      const local = pose3(t.transform.translation, t.transform.rotation);
      if (t.header.frame_id === "odom" && t.child_frame_id === info.root) {
        worldFromBase = { p: local.p.clone().applyQuaternion(worldFromOdom.q).add(worldFromOdom.p),
                          q: worldFromOdom.q.clone().multiply(local.q) };
        placeRoot(worldFromBase);
      } else if (t.header.frame_id === info.root) {
        tools[t.child_frame_id] = local;
      }
    }
    for (const arm of Object.keys(ARMS)) place(arm);
    if (!targets[selected].inBase && grab(selected)) handle.attach(targets[selected].mesh);
    dirty = true;
  });
  new Topic({ ros, name: "/objects", messageType: "lab_msgs/msg/DetectedObjectArray", throttle_rate: 100 }).subscribe((m) => {
    if (!worldFromBase) return;
    for (const o of m.objects) {
      const i = body[o.name];
      const free = i === undefined ? null : info.bodies[i].joints.find((j) => j[0] === 0);
      if (!free) continue;
      const local = pose3(o.pose.position, o.pose.orientation);
      const p = toWorld(local.p), r = worldFromBase.q.clone().multiply(local.q);
      q.splice(free[1], 7, p.x, p.y, p.z, r.w, r.x, r.y, r.z);
    }
    dirty = true;
  });
  function placeRoot(pose) {  // the base's planar joints, so that it is at ``pose``
    if (root === undefined) return;
    const yaw = (o) => new THREE.Euler().setFromQuaternion(o, "ZYX").z;
    const turn = yaw(pose.q) - yaw(rest.quat[root]);
    for (const [type, adr, ax, ay, az, , , , ref] of info.bodies[root].joints) {
      if (type === 3) q[adr] = ref + Math.atan2(Math.sin(turn), Math.cos(turn)) * (Math.sign(az) || 1);
      else if (type === 2) q[adr] = ref + pose.p.clone().sub(rest.pos[root]).dot(new THREE.Vector3(ax, ay, az));
    }
  }
  let frames = 0;
  const draw = () => {
    requestAnimationFrame(draw);
    if (document.visibilityState === "hidden") return;
    if (dirty) { scene.pose(q); dirty = false; }
    renderer.render(scene.world, eye);
    frames += 1;
    renderer.domElement.dataset.frames = String(frames);
  };
  requestAnimationFrame(draw);

  // -- controls ------------------------------------------------------------------------------
  const base = repeater(live.command("/base/cmd_vel", "geometry_msgs/msg/Twist"),
    { linear: { x: 0, y: 0, z: 0 }, angular: { x: 0, y: 0, z: 0 } });
  const held = new Set();
  const moveBase = () => {
    const v = [0, 0, 0];
    for (const k of held) BASE_KEYS[k].forEach((x, i) => { v[i] += x; });
    base.set(held.size ? { linear: { x: 0.2 * v[0], y: 0.2 * v[1], z: 0 }, angular: { x: 0, y: 0, z: 0.5 * v[2] } } : null);
  };
  document.addEventListener("keydown", (e) => {
    if (e.target.closest("input[type=number], textarea")) return;
    const k = e.key.toLowerCase();
    if (k in BASE_KEYS) { held.add(k); moveBase(); e.preventDefault(); return; }
    if (k === "1" || k === "2") { select(k === "1" ? "left" : "right"); return; }
    if (k in TARGET_KEYS && grab(selected)) {
      const t = targets[selected];
      t.inBase.p.add(new THREE.Vector3(...TARGET_KEYS[k]).multiplyScalar(STEP));
      place(selected);
      sendTarget(selected);
      dirty = true;
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
  const trajectory = (topic) => {
    const send = live.command(topic, "trajectory_msgs/msg/JointTrajectory");
    return (names, points) => send({
      header: { stamp: { sec: 0, nanosec: 0 }, frame_id: "" }, joint_names: names,
      points: points.map(([positions, seconds]) => ({
        positions, velocities: [], accelerations: [], effort: [],
        time_from_start: { sec: Math.floor(seconds), nanosec: Math.round((seconds % 1) * 1e9) },
      })),
    });
  };
  const torso = trajectory("/torso/command"), head = trajectory("/head/command");
  $("torso").addEventListener("change", (e) => torso(["torso_lift_joint"], [[Number(e.target.value), 0]]));
  const aim = () => head(["head_pan_joint", "head_tilt_joint"], [[[Number($("pan").value), Number($("tilt").value)], 0]]);
  $("pan").addEventListener("change", aim);
  $("tilt").addEventListener("change", aim);
  for (const side of ["left", "right"]) {
    const send = live.command(`/${side}_gripper/command`, "std_msgs/msg/Float64");
    $(`${side}-gripper`).addEventListener("change", (e) => send({ data: Number(e.target.value) }));
  }
  const arms = { left: trajectory("/left_arm/command"), right: trajectory("/right_arm/command") };
  $("ready").addEventListener("click", () => {  // untuck without sweeping the table
    torso(["torso_lift_joint"], [[0.2, 4]]);
    $("torso").value = "0.2";
    setTimeout(() => {
      for (const [side, ready] of Object.entries(READY)) {
        const names = JOINTS.map((j) => `${side[0]}_${j}_joint`);
        const now = names.map((n) => q[info.joints[n]]);
        const lifted = (pose) => pose.map((x, i) => (i === 1 ? -0.5 : x));
        arms[side](names, [[lifted(now), 2], [lifted(ready), 4], [ready, 5]]);
      }
    }, 4000);
    setTimeout(() => {  // the targets start again from where the tools are now
      for (const arm of Object.keys(ARMS)) { targets[arm].inBase = null; grab(arm); }
    }, 9500);
  });
  document.body.dataset.ready = "yes";  // every handler is in place
}

main().catch((err) => {
  document.getElementById("status").textContent = `the page could not start: ${err}`;
  throw err;
});
