// A match's page following it: while the match is queued or running, ask the API for it
// (GET /api/matches/{id}, same origin) every few seconds and update the page in place:
// its status, the score, what it adds up to, its replays and signature, and each leg's
// row. The words are match-words.js's, the very words of labd/web/matches.py.
// The root's data-status is the status last seen (tests wait on it).

import { ENDED, when } from "./evaluation-words.js";
import {
  goalsWords, ladderWords, legState, replayWords, resultWords, scoreWords, signedWords,
  verdictClass, verdictWords,
} from "./match-words.js";
import { $ } from "./page.js";

const root = $("match");

function show(m) {
  root.dataset.status = m.status;
  const badge = $("status");
  badge.textContent = m.status;
  badge.className = `badge ${m.status}`;
  $("score-a").textContent = String(m.score.a);
  $("score-b").textContent = String(m.score.b);
  $("score-draws").textContent = String(m.score.draws);
  $("score-said").textContent = scoreWords(m);
  const verified = $("verified");
  verified.textContent = replayWords(m.legs, m.verified);
  verified.className = m.verified ? "reproduced" : "muted";
  $("ladder-said").textContent = ladderWords(m);
  $("finished").textContent = when(m.finished);
  $("signed").textContent = signedWords(m);
  for (const leg of m.legs) {
    const row = root.querySelector(`[data-leg="${leg.leg}"]`);
    if (!row) continue;
    const part = (name) => row.querySelector(`[data-part="${name}"]`);
    const state = legState(leg);
    part("state").textContent = state;
    part("state").className = `badge ${state}`;
    part("goals").textContent = goalsWords(leg);
    part("result").textContent = resultWords(leg);
    part("said").textContent = leg.said;
    part("verdict").textContent = verdictWords(leg);
    part("verdict").className = verdictClass(leg);
  }
  $("following").hidden = ENDED.has(m.status);
}

async function follow() {
  const following = $("following");
  try {
    const answer = await fetch(root.dataset.api, {
      headers: { Accept: "application/json" }, cache: "no-store",
    });
    if (!answer.ok) throw new Error(`the lab answered ${answer.status}`);
    const m = await answer.json();
    show(m);
    if (ENDED.has(m.status)) return;
    following.textContent = "This page follows the match as its legs are played.";
  } catch (err) {
    following.textContent = `The lab could not be asked for its progress (${err.message}); asking again.`;
  }
  setTimeout(follow, Number(root.dataset.pollMs));
}

if (root && !ENDED.has(root.dataset.status)) setTimeout(follow, Number(root.dataset.pollMs));
