// Actions that one roslibjs connection advertises and another sends goals to through the
// bridge: feedback and result, cancellation, failure, and a missing action server.
// See harness.mjs for the contract.

import { Action } from "roslib";

import { Inbox, connect, roundTrip, run, withTimeout } from "./harness.mjs";

const FIBONACCI = "example_interfaces/action/Fibonacci";
const LONG = 1000; // goals of this order or more run until cancelled

function fibonacci(order) {
  const sequence = [0, 1];
  while (sequence.length <= order) sequence.push(sequence.at(-1) + sequence.at(-2));
  return sequence.slice(0, order + 1);
}

/**
 * A Fibonacci server on `ros`: it sends each partial sequence as feedback and succeeds;
 * a goal of order LONG or more sends one feedback and waits to be cancelled; a negative
 * order fails. `log` records what the server side saw.
 */
function serveFibonacci(ros, log) {
  const server = new Action({ ros, name: "/fibonacci", actionType: FIBONACCI });
  const partial = new Map();
  server.advertise(
    (goal, id) => {
      log.push({ event: "goal", goal, id });
      if (goal.order < 0) {
        server.setFailed(id);
        return;
      }
      if (goal.order >= LONG) {
        partial.set(id, [0, 1]);
        server.sendFeedback(id, { sequence: [0, 1] });
        return;
      }
      const sequence = fibonacci(goal.order);
      for (let n = 2; n <= sequence.length; n++) {
        server.sendFeedback(id, { sequence: sequence.slice(0, n) });
      }
      server.setSucceeded(id, { sequence });
    },
    (id) => {
      log.push({ event: "cancel", id });
      server.setCanceled(id, { sequence: partial.get(id) ?? [] });
    },
  );
  return server;
}

/** Send a goal; resolves with what the client's callbacks saw once one of them ends it. */
function sendGoal(client, goal, onFeedback = () => {}) {
  const feedback = [];
  let goalId;
  const ended = new Promise((resolve) => {
    goalId = client.sendGoal(
      goal,
      (result) => resolve({ outcome: "result", value: result }),
      (fb) => {
        feedback.push(fb);
        onFeedback(fb, goalId);
      },
      (error) => resolve({ outcome: "failed", value: error }),
    );
  });
  const what = () =>
    `the end of goal ${JSON.stringify(goal)} (feedback so far ${JSON.stringify(feedback)})`;
  return withTimeout(ended, what).then((end) => ({ ...end, feedback, goal_id: goalId }));
}

run({
  // B sends a goal of order 6 to A's server: feedback, then the result.
  async succeed(url) {
    const a = await connect(url, "A");
    const b = await connect(url, "B");
    const log = new Inbox("the server at A");
    serveFibonacci(a, log);
    await roundTrip(a);
    const client = new Action({ ros: b, name: "/fibonacci", actionType: FIBONACCI });
    const end = await sendGoal(client, { order: 6 });
    return { ...end, server: log.items };
  },

  // B cancels a running goal after its first feedback; A's cancel callback sets it canceled.
  async cancel(url) {
    const a = await connect(url, "A");
    const b = await connect(url, "B");
    const log = new Inbox("the server at A");
    serveFibonacci(a, log);
    await roundTrip(a);
    const client = new Action({ ros: b, name: "fibonacci", actionType: FIBONACCI });
    const end = await sendGoal(client, { order: LONG }, (fb, goalId) => client.cancelGoal(goalId));
    return { ...end, server: log.items };
  },

  // B and C each send a long goal to A's server; once both run, B's cancelAllGoals (a call
  // of /fibonacci/_action/cancel_goal with a zero goal id) cancels both.
  async cancel_all(url) {
    const a = await connect(url, "A");
    const b = await connect(url, "B");
    const c = await connect(url, "C");
    const log = new Inbox("the server at A");
    serveFibonacci(a, log);
    await roundTrip(a);
    const running = new Inbox("feedback at B and C");
    const ends = [b, c].map((ros) => {
      const client = new Action({ ros, name: "/fibonacci", actionType: FIBONACCI });
      return { client, end: sendGoal(client, { order: LONG }, (fb) => running.push(fb)) };
    });
    await running.count(2);
    ends[0].client.cancelAllGoals();
    const results = await Promise.all(ends.map((e) => e.end));
    return { results, server: log.items };
  },

  // B sends a long goal to an action the lab serves (action_tutorials_interfaces'
  // Fibonacci, as the ROS 2 tutorials' server); cancelAllGoals cancels it.
  async cancel_all_lab(url) {
    const b = await connect(url, "B");
    const client = new Action({
      ros: b,
      name: "/lab_fibonacci",
      actionType: "action_tutorials_interfaces/action/Fibonacci",
    });
    const end = sendGoal(client, { order: LONG }, () => client.cancelAllGoals());
    return end;
  },

  // B closes its connection while its goal runs; A's server is told to cancel it.
  async client_leaves(url) {
    const a = await connect(url, "A");
    const b = await connect(url, "B");
    const log = new Inbox("the server at A");
    serveFibonacci(a, log);
    await roundTrip(a);
    const client = new Action({ ros: b, name: "/fibonacci", actionType: FIBONACCI });
    client.sendGoal({ order: LONG }, () => {}, () => b.close(), () => {});
    await log.until("a cancel", (items) => items.some((e) => e.event === "cancel"));
    return { server: log.items };
  },

  // A's server fails a goal with setFailed.
  async fail(url) {
    const a = await connect(url, "A");
    const b = await connect(url, "B");
    const log = new Inbox("the server at A");
    serveFibonacci(a, log);
    await roundTrip(a);
    const client = new Action({ ros: b, name: "/fibonacci", actionType: FIBONACCI });
    return { ...(await sendGoal(client, { order: -1 })), server: log.items };
  },

  // Nobody serves /no_such_action.
  async missing(url) {
    const b = await connect(url, "B");
    const client = new Action({ ros: b, name: "/no_such_action", actionType: FIBONACCI });
    return sendGoal(client, { order: 3 });
  },
});
