// Services that one roslibjs connection advertises and another calls through the bridge,
// the ways a call fails, and calls to services that do not exist or are protected.
// See harness.mjs for the contract.

import { Service } from "roslib";

import { Inbox, connect, roundTrip, run, settles } from "./harness.mjs";

function call(ros, name, serviceType, request, timeoutSeconds) {
  const service = new Service({ ros, name, serviceType });
  return settles(`a call of ${name}`, (ok, fail) =>
    service.callService(request, ok, fail, timeoutSeconds),
  );
}

/** Connections A and B, with `name` provided at A by `advertise(service)`. */
async function provided(url, name, serviceType, advertise) {
  const a = await connect(url, "A");
  const b = await connect(url, "B");
  await advertise(new Service({ ros: a, name, serviceType }));
  await roundTrip(a); // the advertise_service is handled
  return b;
}

run({
  // A provides /add_two_ints with a plain callback; B calls it by absolute and relative name.
  async add_two_ints(url) {
    const requests = new Inbox("requests at A");
    const b = await provided(url, "/add_two_ints", "example_interfaces/AddTwoInts", (service) =>
      service.advertise((request, response) => {
        requests.push(request);
        response.sum = request.a + request.b;
        return true;
      }),
    );
    const type = "example_interfaces/srv/AddTwoInts";
    return {
      answer: await call(b, "/add_two_ints", type, { a: 2, b: 40 }),
      relative: await call(b, "add_two_ints", type, { a: -7 }),
      requests: requests.items,
    };
  },

  // A's advertise callback returns false.
  async returns_false(url) {
    const b = await provided(url, "/refuse", "std_srvs/Trigger", (service) =>
      service.advertise(() => false),
    );
    return call(b, "/refuse", "std_srvs/Trigger", {});
  },

  // A's advertiseAsync callback throws.
  async async_throws(url) {
    const b = await provided(url, "/explode", "std_srvs/SetBool", (service) =>
      service.advertiseAsync(async (request) => {
        throw new Error(`motor is on fire (data=${request.data})`);
      }),
    );
    return call(b, "/explode", "std_srvs/SetBool", { data: true });
  },

  // A's advertiseAsync callback answers after an await.
  async async_answers(url) {
    const b = await provided(url, "/switch", "std_srvs/srv/SetBool", (service) =>
      service.advertiseAsync(async (request) => {
        await new Promise((resolve) => setImmediate(resolve));
        return { success: request.data, message: `switched ${request.data ? "on" : "off"}` };
      }),
    );
    return call(b, "/switch", "std_srvs/SetBool", { data: true });
  },

  // A's advertiseAsync callback never answers; B's call says it waits 0.3 s.
  async timeout(url) {
    const b = await provided(url, "/silent", "std_srvs/Empty", (service) =>
      service.advertiseAsync(() => new Promise(() => {})),
    );
    const start = performance.now();
    const outcome = await call(b, "/silent", "std_srvs/Empty", {}, 0.3);
    return { ...outcome, waited_ms: performance.now() - start };
  },

  // B sends a request whose field has the wrong type; A must never see it.
  async bad_request(url) {
    const requests = new Inbox("requests at A");
    const b = await provided(url, "/switch", "std_srvs/SetBool", (service) =>
      service.advertise((request, response) => {
        requests.push(request);
        response.success = true;
        return true;
      }),
    );
    const outcome = await call(b, "/switch", "std_srvs/SetBool", { data: "yes" });
    return { ...outcome, requests: requests.items };
  },

  // A's callback fills the response with a value of the wrong type.
  async invalid_response(url) {
    const b = await provided(url, "/add_two_ints", "example_interfaces/AddTwoInts", (service) =>
      service.advertise((request, response) => {
        response.sum = "lots";
        return true;
      }),
    );
    return call(b, "/add_two_ints", "example_interfaces/AddTwoInts", { a: 1, b: 2 });
  },

  // A receives the call and closes its connection instead of answering.
  async provider_leaves(url) {
    const a = await connect(url, "A");
    const b = await connect(url, "B");
    const service = new Service({ ros: a, name: "/flaky", serviceType: "std_srvs/Trigger" });
    await service.advertiseAsync(() => {
      a.close();
      return new Promise(() => {});
    });
    await roundTrip(a);
    const start = performance.now();
    const outcome = await call(b, "/flaky", "std_srvs/Trigger", {}, 0); // no timeout: wait for ever
    return { ...outcome, waited_ms: performance.now() - start };
  },

  // Nobody provides /no_such_service.
  async nonexistent(url) {
    return call(await connect(url, "B"), "/no_such_service", "std_srvs/Trigger", {});
  },

  // Names under /protected never cross the bridge; a call on one answers {}.
  async protected(url) {
    return call(await connect(url, "B"), "/protected/reset", "std_srvs/Trigger", {});
  },
});
