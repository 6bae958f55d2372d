// What every live robot's page shares: the connection to the robot through the bridge
// (roslibjs, like any client), who drives, the episode, taking and releasing control,
// the camera, and the page's user-experience events on /ux/events.
//
// This is the reference roslibjs application of docs/live.md: nothing here talks to the
// lab's HTTP server except to fetch a reservation's key; the robot is reached only
// through the bridge. A page script adds its own events with
//   window.labLive.ux("study", "question-1", "yes")
// and they land in the drive's record beside the robot's data.

import { Ros, Service, Topic } from "/static/vendor/roslib/roslib.min.js";

const UX_EVERY_MS = 2000;  // frame display latency is summed up this often

/** roslibjs hands a status with an id to that id's listeners only: here every status
 * of the bridge (a refused command, a bad value) is also an event the page shows. */
class LabRos extends Ros {
  handleMessage(message) {
    if (message.op === "status") this.emit("lab-status", message);
    super.handleMessage(message);
  }
}

export function config() {
  return JSON.parse(document.getElementById("live-config").textContent);
}

const $ = (id) => document.getElementById(id);

/**
 * Connect to the robot of this page (``config`` from the server: bridge address,
 * session id, user, interface) and wire the parts every page has. Returns the page's
 * handle, also ``window.labLive``.
 */
export async function connect(cfg) {
  const key = cfg.reservations ? await reservationKey(cfg) : null;
  const ros = new LabRos({});
  const live = {
    ros, config: cfg, driving: false, driver: "", episode: null, key,
    onDriver: [], onEpisode: [],
  };
  window.labLive = live;
  live.status = (text, level = "info") => {
    const line = $("status");
    line.textContent = text;
    line.dataset.level = level;
  };
  ros.on("connection", () => live.status(
    key ? "connected with your slot's key" : cfg.reservations
      ? "connected; watching (driving needs a slot's key)" : "connected", "info"));
  ros.on("close", () => live.status("the bridge closed the connection: reload the page to reconnect", "error"));
  ros.on("error", () => live.status("cannot reach the robot's bridge", "error"));
  ros.on("lab-status", (s) => {
    live.status(s.msg, s.level);
    live.ux("refused", s.id || "", s.msg);
  });
  if (key) ros.authenticate(key.key);  // the first frame, before anything else
  ros.setStatusLevel("warning");
  await ros.connect(cfg.bridge);

  // -- user-experience events ---------------------------------------------------------
  const events = new Topic({ ros, name: "/ux/events", messageType: "lab_msgs/msg/UxEvent", queue_size: 1 });
  live.ux = (kind, what = "", value = "") => {
    events.publish({
      session: cfg.session, kind: String(kind), key: String(what),
      value: typeof value === "string" ? value : JSON.stringify(value),
      browser_ms: performance.timeOrigin + performance.now(),
    });
  };
  const shown = () => live.ux("interface", cfg.interface,
    { assigned: cfg.assigned, ratio: cfg.ratio, robot: cfg.robot, driving: live.driving });
  shown();
  document.addEventListener("keydown", (e) => { if (!e.repeat) live.ux("key", e.key, "down"); });
  document.addEventListener("click", (e) => {
    const target = e.target.closest("button, a, input, canvas, img");
    if (target) live.ux("click", target.id || target.textContent.trim().slice(0, 40));
  });
  window.addEventListener("blur", () => live.ux("focus", "window", "lost"));
  window.addEventListener("focus", () => live.ux("focus", "window", "back"));
  document.addEventListener("visibilitychange", () => live.ux("focus", "tab", document.visibilityState));

  // -- who drives, and the episode ------------------------------------------------------
  new Topic({ ros, name: "/lab/driver", messageType: "lab_msgs/msg/Driver" }).subscribe((m) => {
    const was = live.driving;
    live.driver = m.driver;
    live.driving = m.driver !== "" && m.session === cfg.session;
    if (live.driving && !was) shown();  // in the drive's record from its start
    $("driver").textContent = m.driver ? `${m.driver}${m.interface ? ` (${m.interface})` : ""}` : "nobody";
    $("you").textContent = `${cfg.user}, ${live.driving ? "driving" : "watching"}`;
    $("take").disabled = live.driving;
    $("release").disabled = !live.driving;
    document.body.dataset.driving = live.driving ? "yes" : "no";
    document.body.dataset.seed = String(m.seed);  // the episode being driven (or watched)
    live.onDriver.forEach((f) => f(m));
  });
  new Topic({ ros, name: "/lab/episode", messageType: "lab_msgs/msg/Episode", throttle_rate: 200 })
    .subscribe((m) => {
      live.episode = m;
      $("seed").textContent = `seed ${m.seed}`;
      const t = m.header.stamp.sec + m.header.stamp.nanosec / 1e9;
      $("episode").textContent = `${m.status} · ${t.toFixed(1)} s · reward ${m.total_reward.toFixed(2)}`
        + (m.reason ? ` · ${m.reason}` : "");
      live.onEpisode.forEach((f) => f(m));
    });

  const call = (name, type, request) => new Promise((resolve) => {
    new Service({ ros, name, serviceType: type }).callService(
      request, resolve, (err) => resolve({ success: false, message: String(err) }));
  });
  live.drive = async () => {
    const answer = await call("/lab/drive", "lab_msgs/srv/Drive",
      { session: cfg.session, interface: cfg.interface, user: cfg.user });
    live.status(answer.message, answer.success ? "info" : "warning");
    return answer.success;
  };
  live.release = async () => {
    const answer = await call("/lab/release", "std_srvs/srv/Trigger", {});
    live.status(answer.message, answer.success ? "info" : "warning");
  };
  live.reset = async () => {
    const answer = await call("/lab/reset", "std_srvs/srv/Trigger", {});
    live.status(answer.message, answer.success ? "info" : "warning");
  };
  $("take").addEventListener("click", () => live.drive());
  $("release").addEventListener("click", () => live.release());
  $("reset").addEventListener("click", () => live.reset());

  /** A command topic: ``send(msg)`` publishes it, taking control first when nobody
   * drives (a watcher's commands go out too, and the bridge's refusal is shown). */
  let asking = null;
  live.command = (name, type) => {
    const topic = new Topic({ ros, name, messageType: type, queue_size: 1 });
    return async (msg) => {
      if (!live.driving && !live.driver) {
        asking = asking || live.drive().finally(() => { asking = null; });
        if (!(await asking)) return;
      }
      topic.publish(msg);
    };
  };
  return live;
}

/** A signed-in person's key for the slot running now (null: they watch). */
async function reservationKey(cfg) {
  if (!cfg.signed_in) return null;
  const response = await fetch(`/api/robots/${cfg.robot}/key`, { credentials: "same-origin" });
  if (response.ok) return response.json();
  const problem = await response.json().catch(() => ({}));
  document.getElementById("status").textContent = problem.error || "no slot of yours runs now";
  return null;
}

/**
 * The camera on ``img`` while the page is in view: a background tab unsubscribes (so
 * the robot stops rendering for it) and subscribes again when shown. The time from a
 * frame's arrival to its display is summed up as "latency" events every 2 s.
 */
export function camera(live, img, { onFrame = null } = {}) {
  const topic = new Topic({
    ros: live.ros, name: "/camera/image/compressed",
    messageType: "sensor_msgs/msg/CompressedImage", queue_length: 1,
  });
  let latencies = [], frames = 0, busy = false;
  const show = (m) => {
    frames += 1;
    if (busy) return;  // the browser still decodes the last one: skip, never queue up
    busy = true;
    const arrived = performance.now();
    img.src = `data:image/${m.format.includes("png") ? "png" : "jpeg"};base64,${m.data}`;
    img.decode().then(() => requestAnimationFrame(() => {
      latencies.push(performance.now() - arrived);
      img.dataset.frames = String(Number(img.dataset.frames || 0) + 1);
      if (onFrame) onFrame(m);
    })).catch(() => {}).finally(() => { busy = false; });
  };
  const on = () => topic.subscribe(show);
  const off = () => topic.unsubscribe(show);
  document.addEventListener("visibilitychange", () => {
    if (document.visibilityState === "hidden") off(); else on();
    img.dataset.subscribed = document.visibilityState === "hidden" ? "no" : "yes";
  });
  setInterval(() => {
    if (!latencies.length) return;
    const sorted = latencies.sort((a, b) => a - b);
    const at = (q) => sorted[Math.min(sorted.length - 1, Math.floor(q * sorted.length))];
    live.ux("latency", "camera", { p50_ms: +at(0.5).toFixed(1), max_ms: +at(1).toFixed(1), frames });
    latencies = []; frames = 0;
  }, UX_EVERY_MS);
  if (document.visibilityState !== "hidden") { on(); img.dataset.subscribed = "yes"; }
  return topic;
}

/** Fixed-rate repetition of a velocity while it is held: a live Twist lapses after
 * half a second, as a real base's does. ``set(msg)`` sends it now and every
 * ``periodMs``; ``set(null)`` sends ``zero`` once and stops. */
export function repeater(send, zero, periodMs = 100) {
  let current = null, timer = null;
  return {
    set(msg) {
      const same = JSON.stringify(msg) === JSON.stringify(current);
      current = msg;
      if (msg === null) {
        if (timer) { clearInterval(timer); timer = null; send(zero); }
        return;
      }
      if (!same) send(msg);
      if (!timer) timer = setInterval(() => current && send(current), periodMs);
    },
  };
}
