// The PR2 page's commands (static/live/arms.js) and the forward kinematics its 3D view and
// the record view pose their scenes with (static/scene.js), on three.js as the lab serves it.
import assert from "node:assert/strict";
import { describe, it } from "node:test";

import * as THREE from "../../../web/node_modules/three/build/three.module.js";
import {
  READY, ZERO_TWIST, armJoints, baseTwist, readyPlan, targetEvent, targetPose, targetWords,
  trajectory,
} from "../../../labd/web/static/live/arms.js";
import { kinematics } from "../../../labd/web/static/scene.js";

const close = (actual, expected, within = 1e-9) => {
  assert.equal(actual.length, expected.length);
  actual.forEach((a, i) => assert.ok(Math.abs(a - expected[i]) <= within, `${actual} is not ${expected}`));
};

describe("commands", () => {
  it("the base: keys held add up, at 0.2 m/s and 0.5 rad/s", () => {
    assert.equal(baseTwist(new Set()), null);
    assert.deepEqual(baseTwist(new Set(["w", "a", "q"])),
      { linear: { x: 0.2, y: 0.2, z: 0 }, angular: { x: 0, y: 0, z: 0.5 } });
    assert.deepEqual(baseTwist(new Set(["w", "s"])), ZERO_TWIST);
  });

  it("a trajectory's times are whole seconds and nanoseconds", () => {
    const message = trajectory(["torso_lift_joint"], [[[0.2], 1.25], [[0.3], 4]]);
    assert.deepEqual(message.joint_names, ["torso_lift_joint"]);
    assert.deepEqual(message.points.map((p) => p.time_from_start), [{ sec: 1, nanosec: 250_000_000 }, { sec: 4, nanosec: 0 }]);
    assert.deepEqual(message.points[0].positions, [0.2]);
  });

  it("the ready pose: shoulder lifted while the arm swings, lowered at the end", () => {
    const names = armJoints("left");
    assert.equal(names.length, 7);
    assert.equal(names[1], "l_shoulder_lift_joint");
    const now = [0, 1, 0, 0, 0, 0, 0];
    const plan = readyPlan(now, READY.left);
    assert.deepEqual(plan.map(([, t]) => t), [2, 4, 5]);
    assert.equal(plan[0][0][1], -0.5);
    assert.equal(plan[1][0][1], -0.5);
    assert.deepEqual(plan[2][0], READY.left);
    assert.deepEqual(now, [0, 1, 0, 0, 0, 0, 0]);
  });

  it("a target in base_footprint, and in words", () => {
    const p = { x: 0.61234, y: -0.2, z: 0.9 };
    const message = targetPose(p, { x: 0, y: 0, z: 0, w: 1 });
    assert.equal(message.header.frame_id, "base_footprint");
    assert.deepEqual(message.pose.position, { x: 0.61234, y: -0.2, z: 0.9 });
    assert.equal(targetWords(p), "(0.61, -0.20, 0.90) m");
    assert.deepEqual(targetEvent(p), { x: 0.612, y: -0.2, z: 0.9 });
  });
});

// Bodies as labd/recorder/scene.py describes them: parent, pos, quat (w, x, y, z as
// MuJoCo's), joints [type, qpos address, axis, anchor, ref] (0 free, 2 slide, 3 hinge).
const body = (parent, pos, joints = []) => ({ parent, pos, quat: [0, 0, 0, 1], joints });

describe("forward kinematics", () => {
  it("a hinge turns what hangs from it about its anchor", () => {
    const fk = kinematics(THREE, [
      body(-1, [1, 0, 0], [[3, 0, 0, 0, 1, 0, 0, 0, 0]]),  // a hinge about z at its origin
      body(0, [1, 0, 0]),
    ]);
    fk.forward([Math.PI / 2]);
    close(fk.pos[0].toArray(), [1, 0, 0]);
    close(fk.pos[1].toArray(), [1, 1, 0]);
  });

  it("a hinge's angle counts from its ref, about an anchor off the origin", () => {
    const fk = kinematics(THREE, [body(-1, [0, 0, 0], [[3, 0, 0, 0, 1, 1, 0, 0, 0.5]])]);
    fk.forward([0.5 + Math.PI]);
    close(fk.pos[0].toArray(), [2, 0, 0]);
  });

  it("a slide moves along its axis; a free joint sets the pose (qpos: x y z, w x y z)", () => {
    const fk = kinematics(THREE, [
      body(-1, [0, 0, 1], [[2, 0, 1, 0, 0, 0, 0, 0, 0.1]]),
      body(-1, [0, 0, 0], [[0, 1, 0, 0, 0, 0, 0, 0, 0]]),
    ]);
    const half = Math.SQRT1_2;
    fk.forward([0.6, 5, 6, 7, half, 0, 0, half]);
    close(fk.pos[0].toArray(), [0.5, 0, 1]);
    close(fk.pos[1].toArray(), [5, 6, 7]);
    close(fk.quat[1].toArray(), [0, 0, half, half]);
  });
});
