// The generic live page's action vector and plots (static/live/actions.js).
import assert from "node:assert/strict";
import { describe, it } from "node:test";

import { Rolling, messages } from "../../../labd/web/static/live/actions.js";

// As a task's TaskSpec.actions reaches the page: a template per command topic, and each
// dimension a path in one of them with its bounds.
const ACTIONS = {
  templates: {
    "/action": { type: "std_msgs/msg/Float64MultiArray", message: { layout: { dim: [], data_offset: 0 }, data: [0, 0] } },
    "/cmd_vel": { type: "geometry_msgs/msg/Twist", message: { linear: { x: 0, y: 0, z: 0 }, angular: { x: 0, y: 0, z: 0 } } },
  },
  dimensions: [
    { name: "a0", topic: "/action", path: "data.0", low: -1, high: 1, neutral: 0 },
    { name: "a1", topic: "/action", path: "data.1", low: -1, high: 1, neutral: 0 },
    { name: "v", topic: "/cmd_vel", path: "linear.x", low: -0.5, high: 0.5, neutral: 0 },
  ],
};

describe("the command messages of a vector", () => {
  it("each dimension sets its path, arrays by index", () => {
    const made = messages(ACTIONS, [0.25, -0.5, 0.1]);
    assert.deepEqual(made["/action"].data, [0.25, -0.5]);
    assert.equal(made["/cmd_vel"].linear.x, 0.1);
    assert.deepEqual(made["/cmd_vel"].angular, { x: 0, y: 0, z: 0 });
  });

  it("values are clipped to their bounds", () => {
    const made = messages(ACTIONS, [3, -3, 9]);
    assert.deepEqual(made["/action"].data, [1, -1]);
    assert.equal(made["/cmd_vel"].linear.x, 0.5);
  });

  it("the templates are never changed", () => {
    messages(ACTIONS, [1, 1, 0.5]);
    assert.deepEqual(ACTIONS.templates["/action"].message.data, [0, 0]);
    assert.equal(ACTIONS.templates["/cmd_vel"].message.linear.x, 0);
  });
});

describe("a rolling plot", () => {
  it("keeps the last points of each series, as many series as the first message has", () => {
    const plot = new Rolling(3);
    assert.equal(plot.push(0, Rolling.values({ data: [1, 10] })), true);
    for (let t = 1; t < 5; t += 1) assert.equal(plot.push(t, [1 + t, 10 + t]), false);
    assert.deepEqual(plot.data, [[2, 3, 4], [3, 4, 5], [12, 13, 14]]);
  });

  it("a Float64 is one series", () => {
    const plot = new Rolling(10);
    plot.push(0.5, Rolling.values({ data: 2.5 }));
    assert.deepEqual(plot.data, [[0.5], [2.5]]);
  });

  it("no message yet: the times only", () => {
    assert.deepEqual(new Rolling(5).data, [[]]);
  });
});
