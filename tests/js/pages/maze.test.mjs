// The maze robot's page: keys, stick and pad as velocities, odometry, the goal and the
// tags' places (static/live/maze.js).
import assert from "node:assert/strict";
import { describe, it } from "node:test";

import {
  SPEED, TURN, extendPath, goalWords, inOdom, keyName, keysTwist, odomPose, odomWords, padTwist,
  stick, twist, yaw,
} from "../../../labd/web/static/live/maze.js";

const close = (actual, expected, within = 1e-9) => {
  assert.ok(Math.abs(actual - expected) <= within, `${actual} is not ${expected}`);
};
const turned = (th) => ({ x: 0, y: 0, z: Math.sin(th / 2), w: Math.cos(th / 2) });

describe("driving", () => {
  it("keys held: full speed and turn by their signs; opposite keys cancel", () => {
    assert.deepEqual(keysTwist(new Set(["w"])), twist(SPEED, 0));
    assert.deepEqual(keysTwist(new Set(["ArrowUp", "a"])), twist(SPEED, TURN));
    assert.deepEqual(keysTwist(new Set(["w", "ArrowUp", "d"])), twist(SPEED, -TURN));
    assert.deepEqual(keysTwist(new Set(["w", "s"])), twist(0, 0));
    assert.equal(keysTwist(new Set()), null);
  });

  it("a letter is a key whatever the shift; named keys stay", () => {
    assert.equal(keyName("W"), "w");
    assert.equal(keyName("ArrowLeft"), "ArrowLeft");
  });

  it("the pad: a direction scaled to speed and turn, the centre stops", () => {
    assert.deepEqual(padTwist(1, -1), twist(SPEED, -TURN));
    assert.equal(padTwist(0, 0), null);
  });

  it("the stick: up drives ahead, left turns left, small moves are none; the d-pad at full", () => {
    const pad = (axes, pressed = []) => ({ axes, buttons: Array.from({ length: 16 }, (_, i) => ({ pressed: pressed.includes(i) })) });
    const still = (vw) => vw.map((x) => x + 0);  // -0 is 0 here
    assert.deepEqual(stick(pad([-0.5, -1])), [1, 0.5]);
    assert.deepEqual(still(stick(pad([0.1, -0.14]))), [0, 0]);
    assert.deepEqual(stick(pad([0, 0], [13, 14])), [-1, 1]);
    assert.deepEqual(still(stick({ axes: [], buttons: [] })), [0, 0]);
  });
});

describe("what the robot senses", () => {
  it("heading from a quaternion about z", () => {
    close(yaw(turned(0.7)), 0.7);
    close(yaw(turned(-3)), -3);
  });

  it("odometry in words and as a pose", () => {
    const m = {
      pose: { pose: { position: { x: 1.234, y: -0.5, z: 0 }, orientation: turned(Math.PI / 2) } },
      twist: { twist: { linear: { x: 0.3 }, angular: { z: -1.6 } } },
    };
    const pose = odomPose(m);
    close(pose.th, Math.PI / 2);
    assert.equal(odomWords(m), "x 1.23 m, y -0.50 m, heading 90° · 0.30 m/s, -1.60 rad/s");
  });

  it("the path grows by points 2 cm apart", () => {
    const path = [];
    extendPath(path, 0, 0);
    extendPath(path, 0.01, 0);
    extendPath(path, 0.03, 0);
    assert.deepEqual(path, [[0, 0], [0.03, 0]]);
  });

  it("the goal: its distance, and the turn to face it", () => {
    assert.equal(goalWords({ x: 3, y: 4 }, { x: 0, y: 0, th: 0 }), "5.00 m away (straight line), 53° to the left");
    assert.equal(goalWords({ x: -2, y: 0 }, { x: 0, y: 0, th: Math.PI / 2 }), "2.00 m away (straight line), 90° to the left");
    assert.equal(goalWords({ x: 1, y: -1 }, { x: 0, y: 0, th: 0 }), "1.41 m away (straight line), 45° to the right");
  });

  it("a tag the camera sees ahead and to its right is there in odom", () => {
    // optical frame: z ahead, x right; the camera is 0.12 m ahead of the base
    const [x, y] = inOdom({ x: 1, y: 2, th: Math.PI / 2 }, { x: 0.5, y: 0, z: 0.88 });
    close(x, 1.5);
    close(y, 3);
  });
});
