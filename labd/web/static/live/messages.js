// What the live pages make of the lab's messages, and how their commands go out: functions
// of plain values, with no page and no connection, so that Node's test runner checks them
// (tests/js/pages/live.test.mjs). lab.js wires them to the bridge (roslibjs) and the page.

/** A ROS time (``{sec, nanosec}``) in seconds. */
export const seconds = (stamp) => stamp.sec + stamp.nanosec / 1e9;

/** The status line once the bridge answered. */
export function connectedWords(key, reservations) {
  if (key) return "connected with your slot's key";
  return reservations ? "connected; watching (driving needs a slot's key)" : "connected";
}

/** Who drives, from a /lab/driver message (lab_msgs/msg/Driver), as the page of session
 * ``session`` and person ``user`` shows it. */
export function driverView(m, session, user) {
  const driving = m.driver !== "" && m.session === session;
  return {
    driving,
    driver: m.driver ? `${m.driver}${m.interface ? ` (${m.interface})` : ""}` : "nobody",
    you: `${user}, ${driving ? "driving" : "watching"}`,
  };
}

/** The episode's line, from a /lab/episode message (lab_msgs/msg/Episode). */
export function episodeWords(m) {
  const t = seconds(m.header.stamp);
  return `${m.status} · ${t.toFixed(1)} s · reward ${m.total_reward.toFixed(2)}`
    + (m.reason ? ` · ${m.reason}` : "");
}

/** A /ux/events message (lab_msgs/msg/UxEvent): a value that is not text goes as JSON. */
export function uxEvent(session, kind, what, value, browserMs) {
  return {
    session, kind: String(kind), key: String(what),
    value: typeof value === "string" ? value : JSON.stringify(value),
    browser_ms: browserMs,
  };
}

/** A sensor_msgs/msg/CompressedImage as an image's ``src``. */
export function imageSource(m) {
  return `data:image/${m.format.includes("png") ? "png" : "jpeg"};base64,${m.data}`;
}

/** The camera's display latencies (ms) of one period, summed up for a "latency" event:
 * the median and the largest, to 0.1 ms, and the frames that came; null if none showed. */
export function latencySummary(latencies, frames) {
  if (!latencies.length) return null;
  const sorted = [...latencies].sort((a, b) => a - b);
  const at = (q) => sorted[Math.min(sorted.length - 1, Math.floor(q * sorted.length))];
  return { p50_ms: +at(0.5).toFixed(1), max_ms: +at(1).toFixed(1), frames };
}

/**
 * The commands of a page: ``gate(publish)`` is a ``send(msg)`` that publishes, taking
 * control first (``live.drive()``) when nobody drives; sends that come while control is
 * asked for wait for the same answer, and a refused drive publishes nothing. A watcher's
 * commands go out while someone else drives, and the bridge's refusal is shown.
 */
export function commandGate(live) {
  let asking = null;
  return (publish) => async (msg) => {
    if (!live.driving && !live.driver) {
      asking = asking || live.drive().finally(() => { asking = null; });
      if (!(await asking)) return;
    }
    publish(msg);
  };
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
