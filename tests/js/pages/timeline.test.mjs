// The record view's scrubber: one time every part follows, played at a speed
// (static/timeline.js).
import assert from "node:assert/strict";
import { describe, it } from "node:test";

import {
  Playback, Timeline, before, clockWords, endsWords, speedFor, spriteCell, stripFrames,
} from "../../../labd/web/static/timeline.js";

describe("the index at a time", () => {
  const times = [0, 0.5, 1, 1.5, 2];

  it("is the latest at or before it", () => {
    assert.equal(before(times, 1), 2);
    assert.equal(before(times, 1.49), 2);
    assert.equal(before(times, 9), 4);
  });

  it("before the first, or with none, is 0", () => {
    assert.equal(before(times, -1), 0);
    assert.equal(before([], 3), 0);
  });

  it("agrees with a linear search on uneven times", () => {
    const uneven = [0.1, 0.4, 0.45, 2, 2, 2, 7.5];
    for (let t = 0; t < 8; t += 0.05) {
      let k = 0;
      uneven.forEach((u, i) => { if (u <= t) k = i; });
      assert.equal(before(uneven, t), k, `at ${t}`);
    }
  });
});

describe("the scrubbed time", () => {
  it("every listener follows a seek", () => {
    const time = new Timeline();
    const heard = [];
    time.listen((t) => heard.push(["plot", t]));
    time.listen((t) => heard.push(["camera", t]));
    time.seek(3.5);
    assert.equal(time.now, 3.5);
    assert.deepEqual(heard, [["plot", 3.5], ["camera", 3.5]]);
  });

  it("plays at its speed from where it is, and stops at the end", () => {
    const time = new Timeline();
    const playback = new Playback(time, 10);
    time.seek(2);
    playback.begin(1000);
    assert.equal(playback.step(1500, 4), true);  // half a second at 4×
    assert.equal(time.now, 4);
    assert.equal(playback.step(2500, 4), true);
    assert.equal(time.now, 8);
    assert.equal(playback.step(3500, 4), false);
    assert.equal(time.now, 10);
  });

  it("played from the end, it starts again at 0", () => {
    const time = new Timeline();
    const seen = [];
    time.listen((t) => seen.push(t));
    const playback = new Playback(time, 5);
    time.seek(5);
    playback.begin(0);
    assert.deepEqual(seen, [5, 0]);
    playback.step(100, 1);
    assert.equal(time.now, 0.1);
  });

  it("long records start at 16×, others at 4×", () => {
    assert.equal(speedFor(121), "16");
    assert.equal(speedFor(120), "4");
    assert.equal(speedFor(0), "4");
  });
});

describe("what the view says of a moment", () => {
  const summary = { t: [0, 0.05, 0.1], tick: [0, 1, 2] };

  it("the clock: the time and the tick then", () => {
    assert.equal(clockWords(summary, 0.07), "0.1 s · tick 1");
    assert.equal(clockWords({ t: [], tick: [] }, 0), "0.0 s · tick 0");
  });

  it("how the episodes ended", () => {
    assert.equal(endsWords({ ends: [[12.34, "success"], ["30", "fail"]] }), "success at 12.3 s, fail at 30.0 s");
    assert.equal(endsWords({}), "");
  });

  it("a frame's place in the camera's sprite, and the strip's frames", () => {
    const info = { columns: 4, width: 80, height: 60 };
    assert.deepEqual(spriteCell(info, 0), [0, 0]);
    assert.deepEqual(spriteCell(info, 6), [160, 60]);
    assert.deepEqual(stripFrames(5), [0, 1, 2, 3, 4]);
    assert.deepEqual(stripFrames(30), [0, 3, 6, 9, 12, 15, 18, 21, 24, 27]);
    assert.ok(stripFrames(1000).length <= 12);
  });
});
