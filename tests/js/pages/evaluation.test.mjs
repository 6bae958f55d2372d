// An evaluation's page in words (static/evaluation-words.js); the mean reward's words are
// held to the Python's by tests/labd/test_reward_words.py.
import assert from "node:assert/strict";
import { describe, it } from "node:test";

import {
  cellTitle, countStates, duration, elsewhereWords, percent, rateWords, replayWords, rounded,
  signedWords, verdictClass, when,
} from "../../../labd/web/static/evaluation-words.js";

const row = (episode, fields) => ({ episode, seed: null, reward: null, outcome: null, status: "finished", verified: null, ...fields });

describe("numbers", () => {
  it("round half up, as the Python's pages do", () => {
    assert.equal(rounded(0.0005, 3), "0.001");
    assert.equal(rounded(2.5, 0), "3");
    assert.equal(rounded(17.88, 3), "17.88");
    assert.equal(percent(0.125), "13 %");
  });

  it("compute time in seconds, then minutes; held out says so", () => {
    assert.equal(duration(42.04), "42 s");
    assert.equal(duration(150), "2.5 min");
    assert.equal(duration(null), "held out");
  });

  it("a moment in UTC, to the second", () => {
    assert.equal(when("2026-12-06T07:08:09.5+00:00"), "2026-12-06 07:08:09 UTC");
    assert.equal(when(null), "-");
  });
});

describe("the score", () => {
  const score = { episodes: 20, done: 5, successes: 4, success_rate: null, success_interval: null };

  it("with its interval once every episode ended", () => {
    const ended = { ...score, success_rate: 0.75, success_interval: [0.53, 0.89] };
    assert.equal(rateWords(ended, true), "75 % (53 %–89 %, 95 % Wilson) of 20 episodes");
  });

  it("so far while it runs; held out while it hides", () => {
    assert.equal(rateWords(score, false), "5 of 20 episodes ended so far, 4 succeeded");
    assert.equal(rateWords(score, true), "5 of 20 episodes ended, 4 succeeded");
    assert.equal(rateWords({ ...score, done: null }, false), "held out: the score is shown once every episode has ended");
  });
});

describe("replays", () => {
  it("on another machine of the cluster, only when a cluster replayed", () => {
    assert.equal(elsewhereWords(18, 20), "verified on another machine: 18 of 20");
    assert.equal(elsewhereWords(null, 20), "");
    assert.equal(elsewhereWords(undefined, 20), "");
  });

  it("verified says all", () => {
    assert.equal(replayWords([], true, 1), "✓ verified: all 1 episode replayed identically");
  });

  it("not every row yet", () => {
    assert.equal(replayWords([row(0, {})], false, 3), "not verified: not every episode's replay verified (yet)");
  });

  it("what diverged, what was cancelled, what is still to replay", () => {
    const rows = [
      row(0, { verified: true }), row(1, { verified: false }), row(2, { verified: false }),
      row(3, { status: "cancelled" }), row(4, {}),
    ];
    assert.equal(replayWords(rows, false, 5),
      "not verified: 1 of 5 replayed identically; 2 diverged (episodes 1, 2); 1 cancelled; 1 not replayed yet");
  });

  it("lists ten diverged episodes at most", () => {
    const rows = Array.from({ length: 12 }, (_, i) => row(i, { verified: false }));
    assert.match(replayWords(rows, false, 12), /12 diverged \(episodes 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, \.\.\.\)$/);
  });

  it("a rerun's verdict is coloured by its first word", () => {
    assert.equal(verdictClass("reproduced: same data digest"), "reproduced");
    assert.equal(verdictClass("diverged at tick 3"), "diverged");
    assert.equal(verdictClass("running"), "muted");
  });
});

describe("episodes", () => {
  it("counted by outcome, else by status", () => {
    const rows = [row(0, { outcome: "success" }), row(1, { outcome: "fail" }), row(2, { status: "running" }), row(3, { outcome: "success" })];
    assert.deepEqual(countStates(rows), { success: 2, fail: 1, error: 0, running: 1, queued: 0, cancelled: 0 });
  });

  it("a cell's title: episode, seed and reward where known", () => {
    assert.equal(cellTitle(row(4, { seed: 17, outcome: "success", reward: 0.12345 })), "episode 4, seed 17: success, reward 0.123");
    assert.equal(cellTitle(row(5, { status: "queued" })), "episode 5: queued");
  });

  it("signed: by which key, or why not yet", () => {
    assert.equal(signedWords({ signature: { key: "ab12" }, status: "finished" }), "signed by the lab (key ab12)");
    assert.equal(signedWords({ signature: {}, status: "finished" }), "not signed: this lab has no signing key");
    assert.equal(signedWords({ signature: null, status: "running" }), "signed by the lab when every episode has ended");
  });
});
