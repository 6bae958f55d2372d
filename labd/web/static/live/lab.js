// What every live robot's page shares: the connection to the robot through the bridge
// (roslibjs, like any client), who drives, the episode, taking and releasing control,
// the camera, and the page's user-experience events on /ux/events.
//
// This is the reference roslibjs application of docs/live.md: nothing here talks to the
// lab's HTTP server except to fetch a reservation's key; the robot is reached only
// through the bridge. A page script adds its own events with
//   window.labLive.ux("study", "question-1", "yes")
// and they land in the drive's record beside the robot's data. What the page makes of
// each message is in messages.js (checked in Node); this module wires it to the page.

import { Ros, Service, Topic } from "/static/vendor/roslib/roslib.min.js";
import { $, count, status } from "../page.js";
import {
  commandGate, connectedWords, driverView, episodeWords, imageSource, latencySummary, uxEvent,
} from "./messages.js";

const UX_EVERY_MS = 2000;  // frame display latency is summed up this often

/** roslibjs hands a status with an id to that id's listeners only: here every status
 * of the bridge (a refused command, a bad value) is also an event the page shows. */
class LabRos extends Ros {
  handleMessage(message) {
    if (message.op === "status") this.emit("lab-status", message);
    super.handleMessage(message);
  }
}

/**
 * Connect to the robot of this page (``cfg`` from the server: bridge address, session
 * id, user, interface) and wire the parts every page has. Returns the page's handle,
 * also ``window.labLive``.
 */
export async function connect(cfg) {
  const key = cfg.reservations ? await reservationKey(cfg) : null;
  const ros = new LabRos({});
  const live = {
    ros, config: cfg, driving: false, driver: "", episode: null, key,
    onDriver: [], onEpisode: [], status,
  };
  window.labLive = live;
  ros.on("connection", () => status(connectedWords(key, cfg.reservations), "info"));
  ros.on("close", () => status("the bridge closed the connection: reload the page to reconnect", "error"));
  ros.on("error", () => status("cannot reach the robot's bridge", "error"));
  ros.on("lab-status", (s) => {
    status(s.msg, s.level);
    live.ux("refused", s.id || "", s.msg);
  });
  if (key) ros.authenticate(key.key);  // the first frame, before anything else
  ros.setStatusLevel("warning");
  await ros.connect(cfg.bridge);
  const shown = uxEvents(live);
  driverAndEpisode(live, shown);
  controlServices(live);
  const gate = commandGate(live);
  /** A command topic: ``send(msg)`` publishes it, taking control first when nobody
   * drives (messages.js, commandGate). */
  live.command = (name, type) => {
    const topic = new Topic({ ros, name, messageType: type, queue_size: 1 });
    return gate((msg) => topic.publish(msg));
  };
  return live;
}

/** live.ux(kind, what, value) publishes a user-experience event; the page's keys, clicks
 * and focus are some. Returns ``shown()``, the event of the interface the page shows
 * (sent now, and again when this page starts driving). */
function uxEvents(live) {
  const { ros, config: cfg } = live;
  const events = new Topic({ ros, name: "/ux/events", messageType: "lab_msgs/msg/UxEvent", queue_size: 1 });
  live.ux = (kind, what = "", value = "") => {
    events.publish(uxEvent(cfg.session, kind, what, value, performance.timeOrigin + performance.now()));
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
  return shown;
}

/** Who drives (/lab/driver) and the episode (/lab/episode), on the page and to the page
 * script's listeners (live.onDriver, live.onEpisode). */
function driverAndEpisode(live, shown) {
  const { ros, config: cfg } = live;
  new Topic({ ros, name: "/lab/driver", messageType: "lab_msgs/msg/Driver" }).subscribe((m) => {
    const was = live.driving;
    const view = driverView(m, cfg.session, cfg.user);
    live.driver = m.driver;
    live.driving = view.driving;
    if (live.driving && !was) shown();  // in the drive's record from its start
    $("driver").textContent = view.driver;
    $("you").textContent = view.you;
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
      $("episode").textContent = episodeWords(m);
      live.onEpisode.forEach((f) => f(m));
    });
}

/** live.drive(), live.release() and live.reset(): the lab's services, and their buttons. */
function controlServices(live) {
  const { ros, config: cfg } = live;
  const call = (name, type, request) => new Promise((resolve) => {
    new Service({ ros, name, serviceType: type }).callService(
      request, resolve, (err) => resolve({ success: false, message: String(err) }));
  });
  const said = (answer) => {
    status(answer.message, answer.success ? "info" : "warning");
    return answer.success;
  };
  live.drive = async () => said(await call("/lab/drive", "lab_msgs/srv/Drive",
    { session: cfg.session, interface: cfg.interface, user: cfg.user }));
  live.release = async () => { said(await call("/lab/release", "std_srvs/srv/Trigger", {})); };
  live.reset = async () => { said(await call("/lab/reset", "std_srvs/srv/Trigger", {})); };
  $("take").addEventListener("click", () => live.drive());
  $("release").addEventListener("click", () => live.release());
  $("reset").addEventListener("click", () => live.reset());
}

/** The lab has no slot of this robot for this person now: its words say why. */
export class NoSlot extends Error {}

/** The slot of ``robot`` running now for the signed-in person (its ``key``), or NoSlot
 * with the lab's own words (else ``otherwise``). */
export async function slotKey(robot, otherwise) {
  const response = await fetch(`/api/robots/${robot}/key`, { credentials: "same-origin" });
  if (response.ok) return response.json();
  const problem = await response.json().catch(() => ({}));
  throw new NoSlot(problem.error || otherwise);
}

/** A signed-in person's key for the slot running now (null: they watch, and the status
 * line says why). */
async function reservationKey(cfg) {
  if (!cfg.signed_in) return null;
  return slotKey(cfg.robot, "no slot of yours runs now").catch((err) => {
    if (!(err instanceof NoSlot)) throw err;
    $("status").textContent = err.message;
    return null;
  });
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
    img.src = imageSource(m);
    img.decode().then(() => requestAnimationFrame(() => {
      latencies.push(performance.now() - arrived);
      count(img, "frames");
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
    const summary = latencySummary(latencies, frames);
    if (!summary) return;
    live.ux("latency", "camera", summary);
    latencies = []; frames = 0;
  }, UX_EVERY_MS);
  if (document.visibilityState !== "hidden") { on(); img.dataset.subscribed = "yes"; }
  return topic;
}
