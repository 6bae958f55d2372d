// The record view's time (record.js): one scrubbed time that every part follows, playing
// it at a speed, and what the scrubber and the camera say of a moment. Plain values only,
// so that Node's test runner checks them (tests/js/pages/timeline.test.mjs).

/** The latest index of sorted ``times`` at or before ``t`` (0 if none is). */
export function before(times, t) {
  let lo = 0, hi = times.length - 1;
  if (hi < 0 || t <= times[0]) return 0;
  while (lo < hi) {
    const mid = (lo + hi + 1) >> 1;
    if (times[mid] <= t) lo = mid; else hi = mid - 1;
  }
  return lo;
}

/** The scrubbed time (``now``, in seconds of the record) and its listeners, each called
 * with the new time on every ``seek``. */
export class Timeline {
  constructor() {
    this.now = 0;
    this.listeners = [];
  }

  listen(f) {
    this.listeners.push(f);
  }

  seek(t) {
    this.now = t;
    for (const f of this.listeners) f(t);
  }
}

/**
 * Playing a timeline of ``duration`` seconds at a speed: ``begin(clock)`` at the first
 * animation frame (from the start again if it was at the end), then ``step(clock, speed)``
 * at each one (``clock`` in ms, as requestAnimationFrame gives it), which seeks and says
 * whether to go on: false once the end is reached.
 */
export class Playback {
  constructor(timeline, duration) {
    this.timeline = timeline;
    this.duration = duration;
    this.last = 0;
  }

  begin(clock) {
    this.last = clock;
    if (this.timeline.now >= this.duration) this.timeline.seek(0);
  }

  step(clock, speed) {
    const t = Math.min(this.duration, this.timeline.now + ((clock - this.last) / 1000) * speed);
    this.last = clock;
    this.timeline.seek(t);
    return t < this.duration;
  }
}

/** The playback speed a record starts at: 16× past two minutes, else 4×. */
export const speedFor = (duration) => (duration > 120 ? "16" : "4");

/** The scrubber's clock at ``t``: the time and the tick of the summary's step then. */
export function clockWords(summary, t) {
  const k = before(summary.t, t);
  return `${t.toFixed(1)} s · tick ${summary.tick[k] ?? 0}`;
}

/** How and when the record's episodes ended ("success at 12.5 s, ..."). */
export function endsWords(episode) {
  return (episode.ends || []).map(([t, status]) => `${status} at ${Number(t).toFixed(1)} s`).join(", ");
}

/** Where frame ``k`` is in the camera's sprite (a grid of ``columns``), in pixels. */
export function spriteCell(info, k) {
  return [(k % info.columns) * info.width, Math.floor(k / info.columns) * info.height];
}

/** The frames of the camera's strip: every n-th, at most ``most`` of them. */
export function stripFrames(count, most = 12) {
  const every = Math.max(1, Math.ceil(count / most));
  const frames = [];
  for (let k = 0; k < count; k += every) frames.push(k);
  return frames;
}
