// What an evaluation's page says of it (evaluation.js): the words of labd/web/evaluations.py
// for the same record, rounded the same way (half up), so the page reads as it would
// reloaded. Plain values only: tests/labd/test_reward_words.py holds them to the Python's,
// and tests/js/pages/evaluation.test.mjs checks the rest in Node's test runner.

export const ENDED = new Set(["finished", "cancelled"]);
export const STATES = ["success", "fail", "error", "running", "queued", "cancelled"];
const DIVERGED_LISTED = 10;
const MIN_BOOTSTRAP = 6;  // repository/stats.py: the fewest rewards a 95 % interval takes

export function rounded(value, places) {
  const scale = 10 ** places;
  return String(Math.floor(value * scale + 0.5) / scale);
}

export const percent = (fraction) => `${Math.floor(100 * fraction + 0.5)} %`;
export const plural = (n, word) => (n === 1 ? `${n} ${word}` : `${n} ${word}s`);

export function rateWords(score, ended) {
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

export function rewardWords(score) {
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

export function elsewhereWords(elsewhere, episodes) {
  if (elsewhere === null || elsewhere === undefined) return "";
  return `verified on another machine: ${elsewhere} of ${episodes}`;
}

export function replayWords(rows, verified, episodes) {
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

export function duration(s) {
  if (s === null) return "held out";
  return s < 120 ? `${rounded(s, 1)} s` : `${rounded(s / 60, 1)} min`;
}

/** An episode's state: its outcome once it has one, else its status. */
export const stateOf = (row) => row.outcome || row.status;

export function cellTitle(row) {
  const seed = row.seed === null ? "" : `, seed ${row.seed}`;
  const reward = row.reward === null ? "" : `, reward ${rounded(row.reward, 3)}`;
  return `episode ${row.episode}${seed}: ${stateOf(row)}${reward}`;
}

export function signedWords(e) {
  if (e.signature && Object.keys(e.signature).length) {
    return `signed by the lab (key ${e.signature.key ?? "?"})`;
  }
  if (ENDED.has(e.status)) return "not signed: this lab has no signing key";
  return "signed by the lab when every episode has ended";
}

// As the pages print a moment (labd/web/render.py ``when``).
export const when = (iso) => (iso ? `${new Date(iso).toISOString().slice(0, 19).replace("T", " ")} UTC` : "-");

export function verdictClass(said) {
  if (said.startsWith("reproduced")) return "reproduced";
  return said.startsWith("diverged") ? "diverged" : "muted";
}

/** The episodes by state (every one of STATES, 0 where none is). */
export function countStates(rows) {
  const counts = Object.fromEntries(STATES.map((s) => [s, 0]));
  for (const row of rows) {
    const state = stateOf(row);
    counts[state] = (counts[state] || 0) + 1;
  }
  return counts;
}
