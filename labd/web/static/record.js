// A look inside a trial's record, on its page: plots (uPlot), the camera as a strip of
// frames, a top-down map of the maze with the robot's path, and the scene in 3D
// (three.js, drawn and posed by scene.js, which the live PR2 page shares), all moved
// together by one time scrubber.
//
// It reads the record's summary (GET /api/trials/{id}/summary: labd/recorder/summary.py
// describes it), never the MCAP. Everything it loads comes from this lab.
// For tests and the benchmark, window.labRecord exposes the summary, the scrubber
// (seek), the pose of a body in the 3D scene, and when each part was drawn. The time and
// what is said of it are in timeline.js.

import { $, el } from "./page.js";
import {
  Playback, Timeline, before, clockWords, endsWords, speedFor, spriteCell, stripFrames,
} from "./timeline.js";

const section = $("record");
const view = $("record-view");
const PALETTE = ["#1f77b4", "#d62728", "#2ca02c", "#ff7f0e", "#9467bd", "#8c564b", "#e377c2",
  "#7f7f7f", "#bcbd22", "#17becf"];
const drawn = {};
const time = new Timeline();
const seek = (t) => time.seek(t);
const api = { drawn, seek, ready: null };
window.labRecord = api;

function mark(part) {
  drawn[part] = performance.now();
  section.dataset.drawn = Object.keys(drawn).join(" ");
}

// -- the scrubber ---------------------------------------------------------------------

function scrubber(summary) {
  const duration = summary.duration || 0;
  const range = el("input", { type: "range", min: "0", max: String(duration), step: "any",
    value: "0", "aria-label": "time in the record", id: "record-time" });
  const label = el("span", { class: "clock" });
  const play = el("button", { type: "button", id: "record-play" }, "▶ play");
  const speed = el("select", { "aria-label": "playback speed" },
    ...[1, 4, 16].map((s) => el("option", { value: String(s) }, `${s}×`)));
  speed.value = speedFor(duration);
  const playback = new Playback(time, duration);
  let playing = null;
  play.addEventListener("click", () => {
    if (playing !== null) { cancelAnimationFrame(playing); playing = null; play.textContent = "▶ play"; return; }
    play.textContent = "❚❚ pause";
    playback.begin(performance.now());
    const step = (clock) => {
      if (!playback.step(clock, Number(speed.value))) { playing = null; play.textContent = "▶ play"; return; }
      playing = requestAnimationFrame(step);
    };
    playing = requestAnimationFrame(step);
  });
  range.addEventListener("input", () => seek(Number(range.value)));
  time.listen((t) => {
    range.value = String(t);
    label.textContent = clockWords(summary, t);
  });
  return el("div", { class: "scrub" }, play, speed, range, label,
    el("span", { class: "muted" }, endsWords(summary.episode)));
}

// -- plots ------------------------------------------------------------------------------

function plots(summary, width) {
  const box = el("div", { class: "plots" });
  const t = summary.t;
  for (const plot of summary.plots) {
    const kind = plot.side === "client" ? "command" : "observation";
    const title = plot.group ? `${plot.topic} · ${plot.group}` : plot.topic;
    const holder = el("div", { class: `plot ${kind}` });
    box.append(holder);
    const opts = {
      title: `${title} (${kind})`,
      width, height: 170,
      scales: { x: { time: false } },
      cursor: { sync: { key: "record" }, drag: { x: false, y: false } },
      legend: { show: plot.labels.length <= 12, live: false },
      axes: [{ size: 28 }, { size: 56 }],
      series: [{ label: "s" }, ...plot.labels.map((label, i) => ({
        label, stroke: PALETTE[i % PALETTE.length], width: 1.25, points: { show: false } }))],
    };
    const chart = new uPlot(opts, [t, ...plot.values], holder);
    const line = el("div", { class: "now" });
    chart.over.append(line);
    chart.over.addEventListener("click", () => {
      const x = chart.cursor.left;
      if (x != null && x >= 0) seek(Math.max(0, chart.posToVal(x, "x")));
    });
    time.listen((s) => { line.style.left = `${chart.valToPos(s, "x")}px`; });
  }
  const fixed = summary.constant || [];
  if (fixed.length) {
    const items = fixed.map(([topic, group, label, value]) =>
      `${topic}${group ? " " + group : ""} ${label} = ${value}`);
    box.append(el("details", { class: "constant" },
      el("summary", {}, `${fixed.length} series never changed`), el("p", { class: "mono" }, items.join(" · "))));
  }
  return box;
}

// -- the camera -------------------------------------------------------------------------

async function camera(info) {
  const image = new Image();
  image.src = info.sprite;
  await image.decode();
  const [sw, sh] = info.source;
  const scale = Math.min(1, 320 / sw);
  const canvas = el("canvas", { width: String(Math.round(sw * scale)), height: String(Math.round(sh * scale)),
    id: "record-camera", "aria-label": "the camera" });
  const ctx = canvas.getContext("2d");
  const caption = el("div", { class: "muted" });
  let shown = -1;
  const show = (t) => {
    const k = before(info.t, t);
    if (k === shown) return;
    shown = k;
    const [x, y] = spriteCell(info, k);
    ctx.drawImage(image, x, y, info.width, info.height, 0, 0, canvas.width, canvas.height);
    caption.textContent = `frame ${k + 1} of ${info.t.length}, at ${info.t[k].toFixed(1)} s`;
  };
  show(0);
  time.listen(show);
  const strip = el("div", { class: "strip" });
  for (const k of stripFrames(info.t.length)) {
    const thumb = el("canvas", { width: String(info.width), height: String(info.height), title: `${info.t[k].toFixed(1)} s` });
    thumb.getContext("2d").drawImage(image, ...spriteCell(info, k), info.width, info.height, 0, 0, info.width, info.height);
    thumb.addEventListener("click", () => seek(info.t[k]));
    strip.append(thumb);
  }
  return el("figure", { class: "panel camera" }, canvas, caption, strip);
}

// -- the map ------------------------------------------------------------------------------

function floorMap(map) {
  const xs = map.walls.flatMap((w) => [w[0], w[2]]), ys = map.walls.flatMap((w) => [w[1], w[3]]);
  const [x0, x1, y0, y1] = [Math.min(...xs), Math.max(...xs), Math.min(...ys), Math.max(...ys)];
  const size = 320, scale = size / Math.max(x1 - x0, y1 - y0);
  const canvas = el("canvas", { width: String(Math.ceil((x1 - x0) * scale)), height: String(Math.ceil((y1 - y0) * scale)),
    id: "record-map", "aria-label": "the maze from above, with the robot's path" });
  const ctx = canvas.getContext("2d");
  const px = (x) => (x - x0) * scale, py = (y) => (y1 - y) * scale;  // y up, as in odom
  const path = map.path;
  const base = document.createElement("canvas");
  base.width = canvas.width; base.height = canvas.height;
  const b = base.getContext("2d");
  b.fillStyle = "#f4f1ea"; b.fillRect(0, 0, base.width, base.height);
  if (map.goal) {
    b.fillStyle = "#39b54a";
    b.fillRect(px(map.goal[0]), py(map.goal[3]), (map.goal[2] - map.goal[0]) * scale, (map.goal[3] - map.goal[1]) * scale);
  }
  b.fillStyle = "#9aa3b2";
  for (const [a, c, d, e] of map.walls) b.fillRect(px(a), py(e), (d - a) * scale, (e - c) * scale);
  b.strokeStyle = "#111"; b.lineWidth = 3;
  for (const [, x, y, nx, ny] of map.tags) {  // a tag: a short bar on its wall face
    b.beginPath();
    b.moveTo(px(x - ny * 0.1), py(y + nx * 0.1)); b.lineTo(px(x + ny * 0.1), py(y - nx * 0.1)); b.stroke();
  }
  b.strokeStyle = "rgba(31, 78, 121, 0.75)"; b.lineWidth = 2; b.lineJoin = "round";
  b.beginPath();
  path.x.forEach((x, i) => (i ? b.lineTo(px(x), py(path.y[i])) : b.moveTo(px(x), py(path.y[i]))));
  b.stroke();
  b.fillStyle = "#1f4e79";
  b.beginPath(); b.arc(px(0), py(0), 4, 0, 2 * Math.PI); b.fill();
  const show = (t) => {
    ctx.drawImage(base, 0, 0);
    if (!path.t.length) return;
    const k = before(path.t, t), j = Math.min(k + 1, path.t.length - 1);
    const x = path.x[k], y = path.y[k];
    const heading = Math.atan2(path.y[j] - y, path.x[j] - x);
    ctx.fillStyle = "#c62828";
    ctx.beginPath(); ctx.arc(px(x), py(y), Math.max(4, 0.17 * scale), 0, 2 * Math.PI); ctx.fill();
    if (j !== k) {
      ctx.strokeStyle = "#fff"; ctx.lineWidth = 2; ctx.beginPath(); ctx.moveTo(px(x), py(y));
      ctx.lineTo(px(x + 0.17 * Math.cos(heading)), py(y + 0.17 * Math.sin(heading))); ctx.stroke();
    }
  };
  show(0);
  time.listen(show);
  return el("figure", { class: "panel map" }, canvas,
    el("figcaption", { class: "muted" }, `from above, in ${map.frame}: walls, tags, the goal (green), the robot's path`));
}

// -- the 3D scene -------------------------------------------------------------------------

async function scene3d(info, summary, figure) {
  const THREE = await import("three");
  const { OrbitControls } = await import("three/addons/controls/OrbitControls.min.js");
  const { buildScene, frame } = await import("./scene.js");
  const width = figure.clientWidth || 420, height = Math.round(width * 0.75);
  const renderer = new THREE.WebGLRenderer({ antialias: true });
  renderer.setPixelRatio(Math.min(2, window.devicePixelRatio || 1));
  renderer.setSize(width, height);
  renderer.domElement.id = "record-scene";
  figure.replaceChildren(renderer.domElement, el("div", { class: "muted" }, "drag to turn, scroll to zoom"));
  const scene = await buildScene(THREE, info);
  const q = info.qpos0.slice();
  const pose = (index) => {  // the joint positions at a point: those that move, over the first
    const row = info.qpos.length ? info.qpos[Math.min(index, info.qpos.length - 1)] : [];
    info.moving.forEach((k, j) => { q[k] = row[j]; });
    scene.pose(q);
  };
  pose(0);
  scene.world.updateMatrixWorld(true);
  // a wide scene (a maze) from high up, so that walls hide little; a table from the side
  const from = summary.map ? [-0.15, -0.45, 0.95] : [-0.55, -0.75, 0.6];
  const { camera: eye, centre } = frame(THREE, scene.solids, from, width / height);
  const controls = new OrbitControls(eye, renderer.domElement);
  controls.target.copy(centre);
  controls.update();
  const render = () => renderer.render(scene.world, eye);
  controls.addEventListener("change", render);

  let current = -1;
  const show = (t) => {
    const k = before(summary.t, t);
    if (k === current) return;
    current = k;
    pose(k);
    render();
  };
  show(time.now);
  time.listen(show);
  api.bodyPose = (name) => {
    const i = info.bodies.findIndex((b) => b.name === name);
    return i < 0 ? null : [...scene.pos[i].toArray(), ...scene.quat[i].toArray()];
  };
}

// -- a live page's user-experience events ---------------------------------------------------

function uxEvents(ux) {
  const counts = Object.entries(ux.counts).map(([kind, n]) => `${kind} ${n}`).join(" · ");
  const rows = ux.events.map(([t, kind, key, value]) =>
    el("tr", {}, el("td", { class: "num" }, t.toFixed(2)), el("td", {}, kind), el("td", {}, key),
       el("td", { class: "mono" }, value)));
  const total = Object.values(ux.counts).reduce((a, b) => a + b, 0);
  return el("details", { class: "panel ux", id: "ux-events" },
    el("summary", {}, `The page's events (/ux/events): ${counts}`),
    el("table", {}, el("thead", {}, el("tr", {}, ...["s", "kind", "key", "value"].map((h) => el("th", {}, h)))),
      el("tbody", {}, ...rows)),
    total > ux.events.length ? el("p", { class: "muted" }, `the first ${ux.events.length} of ${total}`) : "");
}

// -- putting it together -----------------------------------------------------------------

async function main() {
  const response = await fetch(section.dataset.summary);
  if (!response.ok) {
    const body = await response.json().catch(() => ({}));
    view.replaceChildren(el("p", { class: "notice" }, `The record's summary is not available: ${body.error || response.status}`));
    return;
  }
  const summary = await response.json();
  api.summary = summary;
  const top = el("div", { class: "views" });
  const plotBox = el("div");
  view.replaceChildren(scrubber(summary), top, plotBox);
  const wide = view.clientWidth || 1000;
  plotBox.append(plots(summary, Math.floor(wide >= 900 ? (wide - 16) / 2 : wide) - 4));
  mark("plots");
  const work = [];
  if (summary.camera) {
    const slot = el("div");
    top.append(slot);
    work.push(camera(summary.camera).then((figure) => { slot.replaceWith(figure); mark("camera"); }));
  }
  if (summary.map) { top.append(floorMap(summary.map)); mark("map"); }
  await Promise.all(work);
  seek(0);
  if (summary.scene) {
    const figure = el("figure", { class: "panel scene" }, el("p", { class: "muted" }, "Loading the 3D scene…"));
    top.append(figure);
    await scene3d(summary.scene, summary, figure);
    mark("scene");
  }
  if (summary.ux) { view.append(uxEvents(summary.ux)); mark("ux"); }
  if (!summary.plots.length && !summary.camera && !summary.scene) {
    view.append(el("p", { class: "muted" }, "The record holds nothing to plot."));
  }
}

api.ready = main().catch((err) => {
  view.replaceChildren(el("p", { class: "notice" }, `The record could not be shown: ${err.message}`));
  throw err;
});
