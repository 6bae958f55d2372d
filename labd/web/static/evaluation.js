// An evaluation's page following it: while the evaluation is queued or running, ask the
// API for it (GET /api/evaluations/{id}, same origin) every few seconds and update the
// page in place: its status, the counts by outcome, the score's words, its replays, each
// episode's cell. The words are evaluation-words.js's, the very words of
// labd/web/evaluations.py for the same record.
// The root's data-status is the status last seen (tests wait on it).

import {
  ENDED, cellTitle, countStates, duration, elsewhereWords, rateWords, replayWords, rewardWords,
  signedWords, stateOf, verdictClass, when,
} from "./evaluation-words.js";
import { $ } from "./page.js";

const root = $("evaluation");

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
  const elsewhere = $("elsewhere");
  elsewhere.textContent = elsewhereWords(score.verified_elsewhere, score.episodes);
  elsewhere.hidden = !elsewhere.textContent;
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
  for (const row of e.rows) {
    const cell = root.querySelector(`[data-episode="${row.episode}"]`);
    if (cell) {
      cell.className = `cell ${stateOf(row)}`;
      cell.title = cellTitle(row);
    }
  }
  const counts = countStates(e.rows);
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
