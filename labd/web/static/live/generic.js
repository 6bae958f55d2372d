// The live page of any task without a page of its own: its camera, its model in 3D
// (three.js, drawn by scene.js from /api/robots/NAME/scene and posed from the robot's
// qpos there, a few times a second), a slider per dimension of its action vector
// (TaskSpec.actions: each slider sets one path in one command message; the messages go
// out through the bridge ten times a second once a slider moved), and a rolling plot of
// each numeric observation topic (std_msgs Float64 and Float64MultiArray).

import * as THREE from "three";
import { OrbitControls } from "three/addons/controls/OrbitControls.min.js";
import { Topic } from "/static/vendor/roslib/roslib.min.js";
import { $, config, count, el, start } from "../page.js";
import { buildScene, frame } from "../scene.js";
import { Rolling, messages } from "./actions.js";
import { camera, connect } from "./lab.js";
import { seconds } from "./messages.js";

const SEND_MS = 100;  // commands while the sliders are in use
const POSE_MS = 250;  // the 3D scene's pose, from the lab's HTTP server
const KEPT = 200;  // points of each plot
const PALETTE = ["#1f77b4", "#d62728", "#2ca02c", "#ff7f0e", "#9467bd", "#8c564b", "#e377c2", "#17becf"];

function sliders(live, actions) {
  const box = $("sliders");
  const vector = actions.dimensions.map((d) => d.neutral);
  const inputs = actions.dimensions.map((d, i) => {
    const input = el("input", { type: "range", min: d.low, max: d.high, step: (d.high - d.low) / 200, value: d.neutral, id: `action-${i}` });
    const shown = el("output", { for: `action-${i}` }, d.neutral.toFixed(3));
    input.addEventListener("input", () => {
      vector[i] = Number(input.value);
      shown.textContent = vector[i].toFixed(3);
      begin();
    });
    box.append(el("p", { class: "slider" }, el("label", { for: `action-${i}` }, d.name), input, shown));
    return { input, shown };
  });
  const senders = Object.fromEntries(Object.entries(actions.templates).map(
    ([topic, { type }]) => [topic, live.command(topic, type)]));
  const send = () => {
    for (const [topic, message] of Object.entries(messages(actions, vector))) senders[topic](message);
    count(box, "sent");
  };
  let timer = null;
  const begin = () => { if (!timer) { send(); timer = setInterval(send, SEND_MS); } };
  $("neutral").addEventListener("click", () => {
    actions.dimensions.forEach((d, i) => {
      vector[i] = d.neutral; inputs[i].input.value = d.neutral; inputs[i].shown.textContent = d.neutral.toFixed(3);
    });
    send();
    clearInterval(timer);
    timer = null;
  });
  live.onDriver.push(() => { if (!live.driving && timer) { clearInterval(timer); timer = null; } });
}

function plots(live, topics) {
  const box = $("plots");
  for (const [name, type] of topics) {
    const holder = el("div", { class: "plot", id: `plot-${name.replaceAll("/", "_")}` });
    box.append(el("h3", {}, name), holder);
    let chart = null;
    const rolling = new Rolling(KEPT);
    new Topic({ ros: live.ros, name, messageType: type, throttle_rate: 100, queue_length: 1 }).subscribe((m) => {
      const values = Rolling.values(m);
      const now = live.episode ? seconds(live.episode.header.stamp) : rolling.t.length;
      if (rolling.push(now, values)) {
        chart = new uPlot({
          width: Math.max(280, holder.clientWidth || 420), height: 140, legend: { show: values.length <= 8 },
          scales: { x: { time: false } },  // simulation seconds
          series: [{ label: "s" }, ...values.map((_, i) => ({ label: `${i}`, stroke: PALETTE[i % PALETTE.length], points: { show: false } }))],
        }, rolling.data, holder);
      }
      chart.setData(rolling.data);
      holder.dataset.points = String(rolling.t.length);
    });
  }
}

async function scene3d(cfg) {
  const holder = $("scene3d");
  const width = holder.clientWidth || 560, height = Math.round(width * 0.7);
  const renderer = new THREE.WebGLRenderer({ antialias: true });
  renderer.setSize(width, height);
  renderer.domElement.id = "generic-scene";
  holder.replaceChildren(renderer.domElement);
  let info = await (await fetch(cfg.scene)).json();
  let scene = await buildScene(THREE, info);
  scene.pose(info.qpos);
  scene.world.updateMatrixWorld(true);
  const { camera: eye, centre } = frame(THREE, scene.solids, [-1.2, -1.0, 0.8], width / height);
  const orbit = new OrbitControls(eye, renderer.domElement);
  orbit.target.copy(centre);
  orbit.update();
  let busy = false;
  setInterval(async () => {  // the pose now (a new episode may bring a new model)
    if (busy || document.visibilityState === "hidden") return;
    busy = true;
    try {
      const next = await (await fetch(cfg.scene)).json();
      if (next.seed !== info.seed) scene = await buildScene(THREE, next);
      info = next;
      scene.pose(info.qpos);
      count(holder, "posed");
    } catch { /* the next one will do */ } finally { busy = false; }
  }, POSE_MS);
  renderer.setAnimationLoop(() => renderer.render(scene.world, eye));
}

start(async () => {
  const live = await connect(config("live-config"));
  const cfg = live.config;
  camera(live, $("camera"));
  if (cfg.actions) sliders(live, cfg.actions);
  plots(live, cfg.plots || []);
  await scene3d(cfg).catch((err) => { $("scene3d").textContent = `the model could not be drawn: ${err}`; });
  document.body.dataset.ready = "yes";
});
