// The playground's checks and the runner frame's messages (static/playground/checks.js),
// with the acorn and CodeMirror the page bundles (web/build.mjs).
import assert from "node:assert/strict";
import { describe, it } from "node:test";

import { Text } from "../../../web/node_modules/@codemirror/state/dist/index.js";
import { parse } from "../../../web/node_modules/acorn/dist/acorn.mjs";
import {
  bridgeAddress, fromRunner, markRange, syntaxError, trialProgress,
} from "../../../labd/web/static/playground/checks.js";

describe("a script's syntax", () => {
  it("a module that parses has no error, top-level await and imports included", () => {
    assert.equal(syntaxError(parse, 'import ROSLIB from "roslib";\nawait Promise.resolve(ROSLIB);\n'), null);
  });

  it("an error names its line and its column (1-based), without acorn's position", () => {
    const error = syntaxError(parse, "const a = 1;\nconst b = ;\n");
    assert.deepEqual(error, { message: "SyntaxError: Unexpected token", line: 2, column: 11 });
  });

  it("a script is a module: strict, so a with statement does not parse", () => {
    const error = syntaxError(parse, "with (Math) { max(1, 2); }");
    assert.equal(error.line, 1);
    assert.match(error.message, /^SyntaxError: /);
  });
});

describe("where a mark goes", () => {
  const doc = Text.of(["const a = 1;", "const b = ;", ""]);

  it("a column marks one character of its line", () => {
    assert.deepEqual(markRange(doc, 2, 11), { from: 23, to: 24 });
  });

  it("no column marks the whole line", () => {
    assert.deepEqual(markRange(doc, 1, 0), { from: 0, to: 12 });
  });

  it("a line past the end marks the last; one before the first, the first", () => {
    assert.deepEqual(markRange(doc, 99), { from: 25, to: 25 });
    assert.deepEqual(markRange(doc, -3), { from: 0, to: 12 });
  });

  it("a column past the line's end stays on it", () => {
    assert.deepEqual(markRange(doc, 1, 40), { from: 12, to: 12 });
  });
});

describe("the runner's messages", () => {
  it("ready: send it the script", () => {
    assert.deepEqual(fromRunner({ op: "ready" }), { do: "run" });
  });

  it("a printed line keeps its level", () => {
    assert.deepEqual(fromRunner({ op: "log", level: "warn", text: "careful" }), { do: "print", text: "careful", level: "warn" });
  });

  it("an error at a line: printed with it, marked there, and the run stops saying why", () => {
    assert.deepEqual(fromRunner({ op: "error", text: "TypeError: x is undefined", line: 7, column: 3 }), {
      do: "fail",
      printed: "TypeError: x is undefined (line 7)",
      mark: { message: "TypeError: x is undefined", line: 7, column: 3 },
      why: "the script failed (line 7): TypeError: x is undefined",
    });
  });

  it("an error with no line marks nothing", () => {
    const said = fromRunner({ op: "error", text: "Error: refused" });
    assert.equal(said.mark, null);
    assert.equal(said.why, "the script failed: Error: refused");
  });

  it("done stops; anything else is no message of the runner's", () => {
    assert.deepEqual(fromRunner({ op: "done" }), { do: "stop", why: "the script ended" });
    for (const m of [null, undefined, {}, { op: "run" }, "ready"]) assert.equal(fromRunner(m), null);
  });
});

describe("running", () => {
  const robots = [{ name: "icreate-1", bridge: "ws://127.0.0.1:9090/robots/icreate-1" }];

  it("a slot's key goes in the bridge's query, escaped", () => {
    assert.equal(bridgeAddress(robots, "icreate-1", null), "ws://127.0.0.1:9090/robots/icreate-1");
    assert.equal(bridgeAddress(robots, "icreate-1", "a+b/c"), "ws://127.0.0.1:9090/robots/icreate-1?key=a%2Bb%2Fc");
  });

  it("a trial's progress: its status, then its outcome and why", () => {
    assert.deepEqual(trialProgress({ id: 4, status: "queued", outcome: null, reason: "" }),
      { text: "trial #4 queued", level: "info", ended: false });
    assert.deepEqual(trialProgress({ id: 4, status: "running", outcome: null, reason: "fetching the commit" }),
      { text: "trial #4 running · fetching the commit", level: "info", ended: false });
    assert.deepEqual(trialProgress({ id: 4, status: "finished", outcome: "error", reason: "it crashed at line 3" }),
      { text: "trial #4 finished · error: it crashed at line 3", level: "error", ended: true });
    assert.equal(trialProgress({ id: 5, status: "cancelled", outcome: null, reason: "" }).ended, true);
  });
});
