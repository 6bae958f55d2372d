// What a match's page says of it (match.js): the words of labd/web/matches.py for the
// same match, so the page reads as it would reloaded. Plain values only (no page), so
// Node can import it.

import { ENDED, plural, signedWords as evaluationSigned } from "./evaluation-words.js";

const DASH = "–";
const DIVERGED_LISTED = 10;
const HOW = { goal: "on goals", time: "at time", forfeit: "by forfeit" };

const team = (side) => side.toUpperCase();
const counts = (leg) => leg.result !== null;

export function scoreWords(m) {
  const n = m.legs.length;
  const ended = m.legs.filter((leg) => ENDED.has(leg.status)).length;
  if (m.status === "cancelled") {
    return `cancelled after ${ended} of ${plural(n, "leg")}: it counts for no one`;
  }
  if (!ENDED.has(m.status)) return `${ended} of ${plural(n, "leg")} ended so far`;
  const counted = m.legs.filter(counts).length;
  if (!counted) return "no leg had a result";
  const s = m.score;
  const lead = s.a > s.b ? "A won the match" : (s.b > s.a ? "B won the match" : "a tie");
  let words = `${lead}, ${s.a}${DASH}${s.b} with ${plural(s.draws, "draw")}`;
  if (counted < n) words += `; ${n - counted} of ${plural(n, "leg")} without a result`;
  return words;
}

export function replayWords(legs, verified) {
  const counted = legs.filter(counts);
  const c = counted.length;
  if (verified) return `✓ verified: all ${plural(c, "counted leg")} replayed identically`;
  if (!c) return "not verified: no leg has a result yet";
  const same = counted.filter((leg) => leg.verified === true).length;
  const diverged = counted.filter((leg) => leg.verified === false).map((leg) => leg.leg);
  const missing = c - same - diverged.length;
  const parts = [`${same} of ${plural(c, "counted leg")} replayed identically`];
  if (diverged.length) {
    const listed = diverged.slice(0, DIVERGED_LISTED).join(", ");
    const more = diverged.length > DIVERGED_LISTED ? ", ..." : "";
    const which = diverged.length === 1 ? "leg" : "legs";
    parts.push(`${diverged.length} diverged (${which} ${listed}${more})`);
  }
  if (missing) parts.push(`${missing} not replayed yet`);
  return `not verified: ${parts.join("; ")}`;
}

export function signedWords(m) {
  return evaluationSigned(m).replace("every episode", "every leg");
}

const entry = (t) => `${t.repository}@${t.commit}`;

export function ladderWords(m) {
  if (entry(m.a) === entry(m.b)) {
    return "not on the ladder: a commit against itself says nothing of its rating";
  }
  if (m.status === "cancelled") return "not on the ladder: a cancelled match counts for no one";
  if (!ENDED.has(m.status)) {
    return "on the ladder once every leg has ended and every counted leg verified";
  }
  if (!m.verified) return "not on the ladder until every counted leg's replay has verified";
  return "counts on the ladder";
}

/** A leg's badge: its outcome once finished, else its status. */
export const legState = (leg) => leg.outcome || leg.status;

export function resultWords(leg) {
  if (leg.result === null) return "-";
  const who = leg.result === "draw" ? "draw" : `${team(leg.result)} won`;
  let words = leg.reason ? `${who} ${HOW[leg.reason]}` : who;
  if (leg.forfeited.length) words += ` (${leg.forfeited.map(team).join(", ")} forfeited)`;
  return words;
}

export function goalsWords(leg) {
  if (leg.goals === null) return "-";
  return `${leg.goals.a ?? 0}${DASH}${leg.goals.b ?? 0}`;
}

export function verdictWords(leg) {
  if (leg.verified === true) return "✓ verified";
  if (leg.verified === false) return "diverged";
  return counts(leg) ? "not yet" : "-";
}

export function verdictClass(leg) {
  if (leg.verified === true) return "reproduced";
  return leg.verified === false ? "diverged" : "muted";
}
