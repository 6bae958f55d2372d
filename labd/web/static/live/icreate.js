// The maze robot's page (icreate-maze): drive it on /cmd_vel with the keyboard, the
// on-screen pad or a gamepad, and see it through one of the rosjs paper's two
// interfaces, drawn at random per session by the lab:
//   A "video": the camera as a live stream;
//   B "perception": the robot's perceptual space, no video: the tags it detects
//     (/ar_tags: ids, boxes and sizes in the image, poses) drawn where the camera sees
//     them and, from above, where they are around the robot, with its odometry path,
//     its bumpers and the goal.
// Both show odometry, bumpers and the goal. Everything comes through the bridge; the
// arithmetic is in maze.js.

import { Topic } from "/static/vendor/roslib/roslib.min.js";
import { $, config, start } from "../page.js";
import { camera, connect } from "./lab.js";
import {
  KEYS, extendPath, goalWords, inOdom, keyName, keysTwist, odomPose, odomWords, padTwist, stick,
  twist,
} from "./maze.js";
import { repeater } from "./messages.js";

async function main() {
  const cfg = config("live-config");
  const live = await connect(cfg);
  const state = { pose: null, path: [], goal: null, bumper: { left: false, right: false },
                  tags: [], seen: new Map(), image: [320, 240] };
  driving(live);
  senses(live, state);
  // -- the interface of this session -----------------------------------------------------
  if (cfg.interface === "video") {
    camera(live, $("camera"));
  } else {
    new Topic({ ros: live.ros, name: "/ar_tags", messageType: "lab_msgs/msg/ArTagArray" }).subscribe((m) => {
      state.tags = m.tags;
      if (state.pose) for (const tag of m.tags) state.seen.set(tag.id, inOdom(state.pose, tag.pose.position));
    });
    perception($("perception"), state);
  }
  document.body.dataset.ready = "yes";  // every handler is in place
}

/** /cmd_vel from the keys held, the on-screen pad and a gamepad. */
function driving(live) {
  const drive = repeater(live.command("/cmd_vel", "geometry_msgs/msg/Twist"), twist(0, 0));
  const held = new Set();
  const fromKeys = () => drive.set(keysTwist(held));
  document.addEventListener("keydown", (e) => {
    const k = keyName(e.key);
    if (!(k in KEYS) || e.target.closest("input, select, textarea")) return;
    e.preventDefault();
    held.add(k);
    fromKeys();
  });
  document.addEventListener("keyup", (e) => {
    if (held.delete(keyName(e.key))) fromKeys();
  });
  window.addEventListener("blur", () => { held.clear(); fromKeys(); });
  for (const button of document.querySelectorAll("#pad button[data-v]")) {
    const v = Number(button.dataset.v), w = Number(button.dataset.w);
    const press = (e) => { e.preventDefault(); button.setPointerCapture?.(e.pointerId); drive.set(padTwist(v, w)); };
    button.addEventListener("pointerdown", press);
    for (const end of ["pointerup", "pointercancel"]) button.addEventListener(end, () => drive.set(null));
  }
  gamepad(live, (v, w) => drive.set(padTwist(v, w)));
}

/** What the robot senses, into ``state`` and on the page: odometry, bumpers, the goal,
 * the camera's size; a new episode starts a new path. */
function senses(live, state) {
  const { ros } = live;
  const showGoal = () => {
    if (state.goal && state.pose) $("goal").textContent = goalWords(state.goal, state.pose);
  };
  new Topic({ ros, name: "/odom", messageType: "nav_msgs/msg/Odometry" }).subscribe((m) => {
    state.pose = odomPose(m);
    extendPath(state.path, state.pose.x, state.pose.y);
    $("odom").textContent = odomWords(m);
    $("odom").dataset.x = state.pose.x.toFixed(4);
    $("odom").dataset.y = state.pose.y.toFixed(4);
    showGoal();
  });
  new Topic({ ros, name: "/bumper", messageType: "lab_msgs/msg/Bumper" }).subscribe((m) => {
    state.bumper = m;
    $("bump-left").classList.toggle("on", m.left);
    $("bump-right").classList.toggle("on", m.right);
  });
  new Topic({ ros, name: "/goal", messageType: "geometry_msgs/msg/PointStamped" }).subscribe((m) => {
    state.goal = m.point;
    showGoal();
  });
  new Topic({ ros, name: "/camera/camera_info", messageType: "sensor_msgs/msg/CameraInfo", throttle_rate: 2000 })
    .subscribe((m) => { state.image = [m.width, m.height]; });
  let seed = null;
  live.onEpisode.push((m) => {
    if (m.seed !== seed) { seed = m.seed; state.path = []; state.seen.clear(); }  // a new episode
  });
}

/** Interface B: the camera's image plane with the tags it detects, and the robot's
 * surroundings from above (odometry path, tags seen, goal, bumpers), redrawn each frame. */
function perception(canvas, state) {
  const g = canvas.getContext("2d");
  let drawn = 0;
  const frame = () => {
    const W = canvas.width, H = canvas.height;
    g.fillStyle = "#f4f6f8"; g.fillRect(0, 0, W, H);
    drawTags(g, state, W / 2, H);
    drawAround(g, state, W / 2, H);
    drawn += 1;
    canvas.dataset.frames = String(drawn);
    canvas.dataset.tags = String(state.tags.length);
    if (document.visibilityState !== "hidden") requestAnimationFrame(frame);
  };
  document.addEventListener("visibilitychange", () => {
    if (document.visibilityState !== "hidden") requestAnimationFrame(frame);
  });
  requestAnimationFrame(frame);
}

/** The left half: what the camera sees, as boxes in its image. */
function drawTags(g, state, half, H) {
  const [iw, ih] = state.image, k = Math.min((half - 20) / iw, (H - 40) / ih);
  const ox = 10, oy = 30;
  g.fillStyle = "#1d2530"; g.fillRect(ox, oy, iw * k, ih * k);
  g.strokeStyle = "#8aa0b8"; g.beginPath(); g.moveTo(ox, oy + ih * k / 2); g.lineTo(ox + iw * k, oy + ih * k / 2); g.stroke();
  g.font = "12px system-ui, sans-serif";
  g.fillStyle = "#333"; g.fillText(`the camera's tags (${state.tags.length})`, ox, 18);
  for (const t of state.tags) {
    const x = ox + (t.cx - t.width / 2) * k, y = oy + (t.cy - t.height / 2) * k;
    g.fillStyle = "rgba(255, 204, 0, 0.35)"; g.fillRect(x, y, t.width * k, t.height * k);
    g.strokeStyle = "#ffcc00"; g.lineWidth = 2; g.strokeRect(x, y, t.width * k, t.height * k);
    g.fillStyle = "#fff"; g.fillText(`#${t.id} ${t.distance.toFixed(2)} m`, x + 3, y - 4 < oy + 10 ? y + 14 : y - 4);
  }
}

/** The right half: the robot's surroundings from above, in odom, the robot at the centre. */
function drawAround(g, state, half, H) {
  const cx = half + half / 2, cy = H / 2 + 10, scale = Math.min(half, H) / 5;  // 5 m across
  const pose = state.pose || { x: 0, y: 0, th: 0 };
  const at = ([x, y]) => [cx - (y - pose.y) * scale, cy - (x - pose.x) * scale];  // x up, y left
  g.fillStyle = "#333"; g.fillText("around the robot (odometry, 5 m across)", half + 10, 18);
  g.save(); g.beginPath(); g.rect(half + 5, 26, half - 10, H - 30); g.clip();
  g.strokeStyle = "#ccd3da"; g.strokeRect(half + 5, 26, half - 10, H - 30);
  g.strokeStyle = "#3a7bd5"; g.lineWidth = 2; g.beginPath();
  state.path.forEach((p, i) => { const [u, v] = at(p); if (i) g.lineTo(u, v); else g.moveTo(u, v); });
  g.stroke();
  if (state.goal) {
    const [u, v] = at([state.goal.x, state.goal.y]);
    g.fillStyle = "rgba(40, 170, 70, 0.5)"; g.fillRect(u - 0.34 * scale, v - 0.34 * scale, 0.68 * scale, 0.68 * scale);
    g.fillStyle = "#185"; g.fillText("goal", u - 12, v + 4);
  }
  const now = new Set(state.tags.map((t) => t.id));
  for (const [id, p] of state.seen) {
    const [u, v] = at(p);
    g.fillStyle = now.has(id) ? "#e0a800" : "#b9b9b9"; g.fillRect(u - 4, v - 4, 8, 8);
    g.fillStyle = "#555"; g.fillText(`#${id}`, u + 6, v + 4);
  }
  g.save(); g.translate(cx, cy); g.rotate(-pose.th);
  g.fillStyle = "#ddd"; g.strokeStyle = "#333"; g.lineWidth = 1.5;
  g.beginPath(); g.arc(0, 0, 0.17 * scale, 0, 2 * Math.PI); g.fill(); g.stroke();
  g.beginPath(); g.moveTo(0, 0); g.lineTo(0, -0.17 * scale); g.stroke();
  g.lineWidth = 5;
  for (const [side, from, to] of [["left", Math.PI, 1.5 * Math.PI], ["right", 1.5 * Math.PI, 2 * Math.PI]]) {
    g.strokeStyle = state.bumper[side] ? "#d33" : "#9ab";
    g.beginPath(); g.arc(0, 0, 0.17 * scale + 3, from, to); g.stroke();
  }
  g.restore();
  g.restore();
}

/** The Gamepad API: the left stick (or the d-pad) drives, polled each animation frame. */
function gamepad(live, set) {
  let last = "", connected = false;
  window.addEventListener("gamepadconnected", (e) => {
    connected = true;
    $("gamepad").textContent = `gamepad: ${e.gamepad.id}`;
    live.ux("gamepad", e.gamepad.id, "connected");
  });
  const poll = () => {
    requestAnimationFrame(poll);
    if (!connected) return;
    const pad = [...navigator.getGamepads()].find((p) => p);
    if (!pad) return;
    const [v, w] = stick(pad);
    const now = `${v.toFixed(2)} ${w.toFixed(2)}`;
    if (now === last) return;
    last = now;
    set(v, w);
  };
  requestAnimationFrame(poll);
}

start(main);
