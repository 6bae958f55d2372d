// An evaluation's page following it: while the evaluation is queued or running, ask the
// API for it (GET /api/evaluations/{id}, same origin) every few seconds and update the
// page in place: its status, the counts by outcome, the score's words, its replays, each
// episode's cell. It says what labd/web/evaluations.py says of the same record, rounded
// the same way (half up), so the page reads as it would reloaded.
// The root's data-status is the status last seen (tests wait on it).

const root = document.getElementById("evaluation");
const ENDED = new Set(["finished", "cancelled"]);
const STATES = ["success", "fail", "error", "running", "queued", "cancelled"];
const DIVERGED_LISTED = 10;
const MIN_BOOTSTRAP = 6;  // repository/stats.py: the fewest rewards a 95 % interval takes
const $ = (id) => document.getElementById(id);

function rounded(value, places) {
  const scale = 10 ** places;
  return String(Math.floor(value * scale + 0.5) / scale);
}

const percent = (fraction) => `${Math.floor(100 * fraction + 0.5)} %`;
const plural = (n, word) => (n === 1 ? `${n} ${word}` : `${n} ${word}s`);

function rateWords(score, ended) {
  if (score.success_rate !== null && score.success_interval !== null) {
    const [low, high] = score.success_interval;
    const words = `${percent(score.success_rate)} (${percent(low)}–${percent(high)}, 95 % Wilson)`;
    return `${words} of ${plural(score.episodes, "episode")}`;
  }
  if (score.done === null || score.successes === null) {
    return "held out: the score is shown once every episode has ended";
  }
  const soFar = ended ? "ended" : "ended so far";
  return `${score.done} of ${plural(score.episodes, "episode")} ${soFar}, ${score.successes} succeeded`;
}

function rewardWords(score) {
  if (score.mean_reward === null) return "no reward yet";
  const words = `mean reward ${rounded(score.mean_reward, 3)}`;
  if (score.reward_interval !== null) {
    const [low, high] = score.reward_interval;
    return `${words} (${rounded(low, 3)} to ${rounded(high, 3)}, 95 % bootstrap)`;
  }
  if (score.done !== null && score.done < MIN_BOOTSTRAP) {
    const few = plural(score.done, "episode");
    return `${words} (${few}: too few for a 95 % interval, which takes ${MIN_BOOTSTRAP})`;
  }
  return `${words} (no 95 % interval: the rewards are all the same, or fewer than ${MIN_BOOTSTRAP})`;
}

function replayWords(rows, verified, episodes) {
  const n = episodes;
  if (verified) return `✓ verified: all ${plural(n, "episode")} replayed identically`;
  if (rows.length < n) return "not verified: not every episode's replay verified (yet)";
  const same = rows.filter((r) => r.verified === true).length;
  const diverged = rows.filter((r) => r.verified === false).map((r) => r.episode);
  const cancelled = rows.filter((r) => r.status === "cancelled").length;
  const missing = n - same - diverged.length - cancelled;
  const parts = [`${same} of ${n} replayed identically`];
  if (diverged.length) {
    const listed = diverged.slice(0, DIVERGED_LISTED).join(", ");
    const more = diverged.length > DIVERGED_LISTED ? ", ..." : "";
    const which = diverged.length === 1 ? "episode" : "episodes";
    parts.push(`${diverged.length} diverged (${which} ${listed}${more})`);
  }
  if (cancelled) parts.push(`${cancelled} cancelled`);
  if (missing) parts.push(`${missing} not replayed yet`);
  return `not verified: ${parts.join("; ")}`;
}

function duration(s) {
  if (s === null) return "held out";
  return s < 120 ? `${rounded(s, 1)} s` : `${rounded(s / 60, 1)} min`;
}
const stateOf = (row) => row.outcome || row.status;

function cellTitle(row) {
  const seed = row.seed === null ? "" : `, seed ${row.seed}`;
  const reward = row.reward === null ? "" : `, reward ${rounded(row.reward, 3)}`;
  return `episode ${row.episode}${seed}: ${stateOf(row)}${reward}`;
}

function signedWords(e) {
  if (e.signature && Object.keys(e.signature).length) {
    return `signed by the lab (key ${e.signature.key ?? "?"})`;
  }
  if (ENDED.has(e.status)) return "not signed: this lab has no signing key";
  return "signed by the lab when every episode has ended";
}

// As the pages print a moment (labd/web/render.py ``when``).
const when = (iso) => (iso ? `${new Date(iso).toISOString().slice(0, 19).replace("T", " ")} UTC` : "-");

function verdictClass(said) {
  if (said.startsWith("reproduced")) return "reproduced";
  return said.startsWith("diverged") ? "diverged" : "muted";
}

function show(e) {
  const ended = ENDED.has(e.status);
  const score = e;  // the score's fields are the evaluation's own
  root.dataset.status = e.status;
  const badge = $("status");
  badge.textContent = e.status;
  badge.className = `badge ${e.status}`;
  $("rate").textContent = rateWords(score, ended);
  $("reward").textContent = rewardWords(score);
  const verified = $("verified");
  verified.textContent = replayWords(e.rows, score.verified, score.episodes);
  verified.className = score.verified ? "reproduced" : "muted";
  const partial = $("partial");
  partial.textContent = `partial: ${e.partial_reason}; not every episode counted, so the`
    + " leaderboard leaves it out";
  partial.hidden = !e.partial;
  const reproduced = $("reproduced");
  if (reproduced && e.reproduced) {
    reproduced.textContent = e.reproduced;
    reproduced.className = verdictClass(e.reproduced);
  }
  $("finished").textContent = when(e.finished);
  $("compute").textContent = duration(score.compute_seconds);
  $("signed").textContent = signedWords(e);
  const counts = Object.fromEntries(STATES.map((s) => [s, 0]));
  for (const row of e.rows) {
    const state = stateOf(row);
    counts[state] = (counts[state] || 0) + 1;
    const cell = root.querySelector(`[data-episode="${row.episode}"]`);
    if (cell) {
      cell.className = `cell ${state}`;
      cell.title = cellTitle(row);
    }
  }
  for (const node of root.querySelectorAll("[data-count]")) {
    node.textContent = String(counts[node.dataset.count] || 0);
  }
  $("following").hidden = ended;
}

async function follow() {
  const following = $("following");
  try {
    const answer = await fetch(root.dataset.api, {
      headers: { Accept: "application/json" }, cache: "no-store",
    });
    if (!answer.ok) throw new Error(`the lab answered ${answer.status}`);
    const e = await answer.json();
    show(e);
    if (ENDED.has(e.status)) return;
    following.textContent = "This page follows the evaluation as its episodes run.";
  } catch (err) {
    following.textContent = `The lab could not be asked for its progress (${err.message}); asking again.`;
  }
  setTimeout(follow, Number(root.dataset.pollMs));
}

if (root && !ENDED.has(root.dataset.status)) setTimeout(follow, Number(root.dataset.pollMs));
