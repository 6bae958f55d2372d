// The generic live page's arithmetic (generic.js): the command messages a vector of
// actions stands for, and the rolling series of a plot. Plain values only, so that Node's
// test runner checks them (tests/js/pages/generic.test.mjs).

/** The command messages a vector stands for (as registry.Actions.messages does): each
 * dimension sets one path of one topic's template, clipped to its bounds. */
export function messages(actions, vector) {
  const made = {};
  for (const [topic, { message }] of Object.entries(actions.templates)) made[topic] = structuredClone(message);
  actions.dimensions.forEach((d, i) => {
    const path = d.path.split(".");
    let here = made[d.topic];
    for (const key of path.slice(0, -1)) here = here[Array.isArray(here) ? Number(key) : key];
    const last = path[path.length - 1];
    here[Array.isArray(here) ? Number(last) : last] = Math.min(d.high, Math.max(d.low, vector[i]));
  });
  return made;
}

/** The last ``kept`` points of a topic's plot: ``t`` and one series per value of its
 * messages (as many as the first message has). */
export class Rolling {
  constructor(kept) {
    this.kept = kept;
    this.t = [];
    this.series = null;
  }

  /** The values of a std_msgs Float64 or Float64MultiArray message. */
  static values(m) {
    return Array.isArray(m.data) ? m.data : [m.data];
  }

  /** Add ``values`` at ``t``, dropping the oldest point past ``kept``; true for the first. */
  push(t, values) {
    const first = this.series === null;
    if (first) this.series = values.map(() => []);
    this.t.push(t);
    values.forEach((v, i) => this.series[i]?.push(v));
    if (this.t.length > this.kept) { this.t.shift(); this.series.forEach((s) => s.shift()); }
    return first;
  }

  /** uPlot's data: the times, then each series. */
  get data() {
    return [this.t, ...(this.series || [])];
  }
}
