// A benchmark run's page following it: while the run is queued or running, ask the API
// for it (GET /api/benchmark-runs/{id}, same origin) every few seconds, and reload the
// page once its status or its count of ended episodes has moved, so every number, the
// per-task table and the profile are the server's own (labd/web/benchmarks.py).

import { $ } from "./page.js";

const root = $("benchmark-run");

async function follow() {
  try {
    const answer = await fetch(root.dataset.api, { headers: { Accept: "application/json" } });
    if (answer.ok) {
      const run = await answer.json();
      if (run.status !== root.dataset.status || String(run.done) !== root.dataset.done) {
        window.location.reload();
        return;
      }
    }
  } catch (_err) {
    // the lab is restarting or the network is down: ask again at the next tick
  }
  window.setTimeout(follow, Number(root.dataset.pollMs));
}

if (root && !["finished", "cancelled"].includes(root.dataset.status)) {
  window.setTimeout(follow, Number(root.dataset.pollMs));
}
