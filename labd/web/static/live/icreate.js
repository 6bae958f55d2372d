// The maze robot's page (icreate-maze): drive it on /cmd_vel with the keyboard, the
// on-screen pad or a gamepad, and see it through one of the rosjs paper's two
// interfaces, drawn at random per session by the lab:
//   A "video": the camera as a live stream;
//   B "perception": the robot's perceptual space, no video: the tags it detects
//     (/ar_tags: ids, boxes and sizes in the image, poses) drawn where the camera sees
//     them and, from above, where they are around the robot, with its odometry path,
//     its bumpers and the goal.
// Both show odometry, bumpers and the goal. Everything comes through the bridge.

import { Topic } from "/static/vendor/roslib/roslib.min.js";
import { camera, config, connect, repeater } from "/static/live/lab.js";

const SPEED = 0.3, TURN = 1.6;  // m/s and rad/s at full stick
const KEYS = {
  ArrowUp: [1, 0], w: [1, 0], ArrowDown: [-1, 0], s: [-1, 0],
  ArrowLeft: [0, 1], a: [0, 1], ArrowRight: [0, -1], d: [0, -1],
};
const CAMERA_IN_BASE = 0.12;  // m ahead of base_link (docs/tasks.md)

const $ = (id) => document.getElementById(id);
const yaw = (q) => Math.atan2(2 * (q.w * q.z + q.x * q.y), 1 - 2 * (q.y * q.y + q.z * q.z));

async function main() {
  const cfg = config();
  const live = await connect(cfg);
  const { ros } = live;
  const state = { pose: null, path: [], goal: null, bumper: { left: false, right: false },
                  tags: [], seen: new Map(), image: [320, 240] };

  // -- driving ---------------------------------------------------------------------------
  const send = live.command("/cmd_vel", "geometry_msgs/msg/Twist");
  const twist = (v, w) => ({ linear: { x: v, y: 0, z: 0 }, angular: { x: 0, y: 0, z: w } });
  const drive = repeater(send, twist(0, 0));
  const held = new Set();
  const fromKeys = () => {
    let v = 0, w = 0;
    for (const k of held) { v += KEYS[k][0]; w += KEYS[k][1]; }
    drive.set(held.size ? twist(SPEED * Math.sign(v), TURN * Math.sign(w)) : null);
  };
  document.addEventListener("keydown", (e) => {
    const k = e.key.length === 1 ? e.key.toLowerCase() : e.key;
    if (!(k in KEYS) || e.target.closest("input, select, textarea")) return;
    e.preventDefault();
    held.add(k);
    fromKeys();
  });
  document.addEventListener("keyup", (e) => {
    const k = e.key.length === 1 ? e.key.toLowerCase() : e.key;
    if (held.delete(k)) fromKeys();
  });
  window.addEventListener("blur", () => { held.clear(); fromKeys(); });
  for (const button of document.querySelectorAll("#pad button[data-v]")) {
    const v = Number(button.dataset.v), w = Number(button.dataset.w);
    const press = (e) => { e.preventDefault(); button.setPointerCapture?.(e.pointerId); drive.set(v || w ? twist(SPEED * v, TURN * w) : null); };
    button.addEventListener("pointerdown", press);
    for (const end of ["pointerup", "pointercancel"]) button.addEventListener(end, () => drive.set(null));
  }
  gamepad(live, (v, w) => drive.set(v || w ? twist(SPEED * v, TURN * w) : null));

  // -- what the robot senses -------------------------------------------------------------
  new Topic({ ros, name: "/odom", messageType: "nav_msgs/msg/Odometry" }).subscribe((m) => {
    const p = m.pose.pose.position, th = yaw(m.pose.pose.orientation);
    state.pose = { x: p.x, y: p.y, th };
    const last = state.path[state.path.length - 1];
    if (!last || Math.hypot(last[0] - p.x, last[1] - p.y) > 0.02) state.path.push([p.x, p.y]);
    $("odom").textContent = `x ${p.x.toFixed(2)} m, y ${p.y.toFixed(2)} m, heading ${(th * 180 / Math.PI).toFixed(0)}°`
      + ` · ${m.twist.twist.linear.x.toFixed(2)} m/s, ${m.twist.twist.angular.z.toFixed(2)} rad/s`;
    $("odom").dataset.x = p.x.toFixed(4);
    $("odom").dataset.y = p.y.toFixed(4);
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
  function showGoal() {
    if (!state.goal || !state.pose) return;
    const dx = state.goal.x - state.pose.x, dy = state.goal.y - state.pose.y;
    let bearing = Math.atan2(dy, dx) - state.pose.th;
    bearing = Math.atan2(Math.sin(bearing), Math.cos(bearing));
    $("goal").textContent = `${Math.hypot(dx, dy).toFixed(2)} m away (straight line), `
      + `${Math.abs(bearing * 180 / Math.PI).toFixed(0)}° to the ${bearing >= 0 ? "left" : "right"}`;
  }

  // -- the interface of this session -----------------------------------------------------
  if (cfg.interface === "video") {
    camera(live, $("camera"));
  } else {
    new Topic({ ros, name: "/ar_tags", messageType: "lab_msgs/msg/ArTagArray" }).subscribe((m) => {
      state.tags = m.tags;
      if (state.pose) for (const tag of m.tags) state.seen.set(tag.id, inOdom(state.pose, tag.pose.position));
    });
    perception($("perception"), state);
  }
  document.body.dataset.ready = "yes";  // every handler is in place
}

/** A tag's centre in odom, from its position in the camera's optical frame. */
function inOdom(pose, p) {
  const ahead = CAMERA_IN_BASE + p.z, left = -p.x;
  const c = Math.cos(pose.th), s = Math.sin(pose.th);
  return [pose.x + c * ahead - s * left, pose.y + s * ahead + c * left];
}

/** Interface B: the camera's image plane with the tags it detects, and the robot's
 * surroundings from above (odometry path, tags seen, goal, bumpers), redrawn each frame. */
function perception(canvas, state) {
  const g = canvas.getContext("2d");
  let drawn = 0;
  const frame = () => {
    const W = canvas.width, H = canvas.height, half = W / 2;
    g.fillStyle = "#f4f6f8"; g.fillRect(0, 0, W, H);
    // left: what the camera sees, as boxes in its image
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
    // right: the robot's surroundings from above, in odom, the robot at the centre
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
    const dead = (x) => (Math.abs(x) < 0.15 ? 0 : x);
    let v = -dead(pad.axes[1] || 0), w = -dead(pad.axes[0] || 0);
    if (pad.buttons[12]?.pressed) v = 1;
    if (pad.buttons[13]?.pressed) v = -1;
    if (pad.buttons[14]?.pressed) w = 1;
    if (pad.buttons[15]?.pressed) w = -1;
    const now = `${v.toFixed(2)} ${w.toFixed(2)}`;
    if (now === last) return;
    last = now;
    set(v, w);
  };
  requestAnimationFrame(poll);
}

main().catch((err) => {
  document.getElementById("status").textContent = `the page could not start: ${err}`;
  throw err;
});
