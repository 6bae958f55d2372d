// The live pages' handling of the lab's messages and of their commands (static/live/messages.js).
import assert from "node:assert/strict";
import { describe, it, mock } from "node:test";

import {
  commandGate, connectedWords, driverView, episodeWords, imageSource, latencySummary, repeater,
  seconds, uxEvent,
} from "../../../labd/web/static/live/messages.js";

const episode = (status, sec, nanosec, reward, reason = "") => ({
  status, header: { stamp: { sec, nanosec } }, total_reward: reward, reason, seed: 3,
});

describe("who drives and the episode", () => {
  it("a ROS time is seconds", () => {
    assert.equal(seconds({ sec: 12, nanosec: 500_000_000 }), 12.5);
  });

  it("this session drives only when the driver's session is its own", () => {
    const mine = driverView({ driver: "ada", interface: "video", session: "s1" }, "s1", "ada");
    assert.deepEqual(mine, { driving: true, driver: "ada (video)", you: "ada, driving" });
    const theirs = driverView({ driver: "bob", interface: "", session: "s2" }, "s1", "ada");
    assert.deepEqual(theirs, { driving: false, driver: "bob", you: "ada, watching" });
  });

  it("nobody drives: an empty driver, even with this session's id", () => {
    const view = driverView({ driver: "", interface: "", session: "s1" }, "s1", "ada");
    assert.equal(view.driving, false);
    assert.equal(view.driver, "nobody");
  });

  it("the episode's line: status, simulated time, reward, and why it ended", () => {
    assert.equal(episodeWords(episode("running", 4, 250_000_000, 1.234)), "running · 4.3 s · reward 1.23");
    assert.equal(episodeWords(episode("fail", 60, 0, 0, "time limit")), "fail · 60.0 s · reward 0.00 · time limit");
  });

  it("the connected line says whether this page may drive", () => {
    assert.equal(connectedWords({ key: "k" }, true), "connected with your slot's key");
    assert.equal(connectedWords(null, true), "connected; watching (driving needs a slot's key)");
    assert.equal(connectedWords(null, false), "connected");
  });
});

describe("user-experience events and the camera", () => {
  it("a value that is not text goes as JSON; kind and key as text", () => {
    assert.deepEqual(uxEvent("s1", "latency", 7, { p50_ms: 3 }, 1000.5), {
      session: "s1", kind: "latency", key: "7", value: '{"p50_ms":3}', browser_ms: 1000.5,
    });
    assert.equal(uxEvent("s1", "key", "w", "down", 0).value, "down");
  });

  it("a compressed image is a data URL of its format", () => {
    assert.equal(imageSource({ format: "rgb8; png compressed bgr8", data: "AAA" }), "data:image/png;base64,AAA");
    assert.equal(imageSource({ format: "jpeg", data: "BBB" }), "data:image/jpeg;base64,BBB");
  });

  it("latencies sum up as their median and largest, to 0.1 ms; none is no event", () => {
    assert.equal(latencySummary([], 4), null);
    const latencies = [30.04, 10, 20.06, 40];
    assert.deepEqual(latencySummary(latencies, 9), { p50_ms: 30, max_ms: 40, frames: 9 });
    assert.deepEqual(latencies, [30.04, 10, 20.06, 40]);  // the caller's list is left as it was
  });
});

describe("commands", () => {
  const page = (driving, driver, answers) => {
    const asked = [];
    return {
      driving, driver, asked,
      drive: async () => { asked.push("drive"); return answers.shift(); },
    };
  };

  it("nobody drives: control is taken first, once for sends that come meanwhile", async () => {
    const live = page(false, "", [true]);
    const sent = [];
    const send = commandGate(live)((m) => sent.push(m));
    await Promise.all([send(1), send(2)]);
    assert.deepEqual(live.asked, ["drive"]);
    assert.deepEqual(sent, [1, 2]);
  });

  it("a refused drive publishes nothing, and the next send asks again", async () => {
    const live = page(false, "", [false, true]);
    const sent = [];
    const send = commandGate(live)((m) => sent.push(m));
    await send("refused");
    assert.deepEqual(sent, []);
    await send("taken");
    assert.deepEqual(live.asked, ["drive", "drive"]);
    assert.deepEqual(sent, ["taken"]);
  });

  it("driving, or watching someone drive: the command goes out as it is", async () => {
    for (const live of [page(true, "ada", []), page(false, "bob", [])]) {
      const sent = [];
      await commandGate(live)((m) => sent.push(m))("go");
      assert.deepEqual(sent, ["go"]);
      assert.deepEqual(live.asked, []);
    }
  });

  it("a held velocity repeats every period; null sends zero once and stops", () => {
    mock.timers.enable({ apis: ["setInterval"] });
    try {
      const sent = [];
      const held = repeater((m) => sent.push(m), "zero", 100);
      held.set("ahead");
      assert.deepEqual(sent, ["ahead"]);
      mock.timers.tick(250);
      assert.deepEqual(sent, ["ahead", "ahead", "ahead"]);
      held.set("ahead");  // the same again: no extra send
      held.set("left");
      mock.timers.tick(100);
      assert.deepEqual(sent.slice(3), ["left", "left"]);
      held.set(null);
      held.set(null);  // once only
      mock.timers.tick(500);
      assert.deepEqual(sent.slice(5), ["zero"]);
    } finally {
      mock.timers.reset();
    }
  });
});
