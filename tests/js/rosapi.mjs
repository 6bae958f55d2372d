// The /rosapi services as roslibjs' Ros helpers and Param call them.
// See harness.mjs for the contract.

import { Action, Param, Service, Topic } from "roslib";

import { connect, roundTrip, run, succeeds } from "./harness.mjs";

run({
  // A advertises a topic, a service and an action; B asks the graph about them.
  async graph(url) {
    const a = await connect(url, "A");
    const b = await connect(url, "B");
    const probe = new Topic({ ros: a, name: "/rosapi_probe", messageType: "geometry_msgs/Twist" });
    probe.advertise();
    const service = new Service({
      ros: a,
      name: "/probe_service",
      serviceType: "std_srvs/Trigger",
    });
    await service.advertise((_, response) => {
      response.success = true;
      return true;
    });
    new Action({
      ros: a,
      name: "/fib_probe",
      actionType: "example_interfaces/action/Fibonacci",
    }).advertise(() => {});
    await roundTrip(a);

    const ask = (what, start) => succeeds(what, start);
    const details = await ask("getMessageDetails", (ok, fail) =>
      b.getMessageDetails("geometry_msgs/Twist", ok, fail),
    );
    const publishers = await ask("Topic.getPublishers", (ok, fail) =>
      new Topic({ ros: b, name: "/rosapi_probe" }).getPublishers(ok, fail),
    );
    return {
      publishers,
      publisher_details: await ask("getNodeDetails", (ok, fail) =>
        b.getNodeDetails(publishers[0], ok, fail),
      ),
      topics: await ask("getTopics", (ok, fail) => b.getTopics(ok, fail)),
      topics_and_raw_types: await ask("getTopicsAndRawTypes", (ok, fail) =>
        b.getTopicsAndRawTypes(ok, fail),
      ),
      topics_for_type: await ask("getTopicsForType", (ok, fail) =>
        b.getTopicsForType("geometry_msgs/msg/Twist", ok, fail),
      ),
      services: await ask("getServices", (ok, fail) => b.getServices(ok, fail)),
      services_for_type: await ask("getServicesForType", (ok, fail) =>
        b.getServicesForType("std_srvs/Trigger", ok, fail),
      ),
      nodes: await ask("getNodes", (ok, fail) => b.getNodes(ok, fail)),
      topic_type: await ask("getTopicType", (ok, fail) =>
        b.getTopicType("/rosapi_probe", ok, fail),
      ),
      unknown_topic_type: await ask("getTopicType of an unknown topic", (ok, fail) =>
        b.getTopicType("/no_such_topic", ok, fail),
      ),
      service_type: await ask("getServiceType", (ok, fail) =>
        b.getServiceType("/rosapi/topics", ok, fail),
      ),
      probe_service_type: await ask("getServiceType", (ok, fail) =>
        b.getServiceType("/probe_service", ok, fail),
      ),
      request_details: await ask("getServiceRequestDetails", (ok, fail) =>
        b.getServiceRequestDetails("example_interfaces/AddTwoInts", ok, fail),
      ),
      response_details: await ask("getServiceResponseDetails", (ok, fail) =>
        b.getServiceResponseDetails("example_interfaces/srv/AddTwoInts", ok, fail),
      ),
      message_details: details,
      decoded: b.decodeTypeDefs(details),
      action_servers: await ask("getActionServers", (ok, fail) => b.getActionServers(ok, fail)),
    };
  },

  // B sets parameters with Param.set; A reads them back with Param.get.
  async params(url) {
    const a = await connect(url, "A");
    const b = await connect(url, "B");
    const value = { limit: 1.5, axes: ["x", "y"], enabled: true, note: "ünïcode" };
    const set = (ros, name, v) =>
      succeeds(`Param(${name}).set`, (ok, fail) => new Param({ ros, name }).set(v, ok, fail));
    const get = (ros, name) =>
      succeeds(`Param(${name}).get`, (ok, fail) => new Param({ ros, name }).get(ok, fail));
    await set(b, "/max_speed", value);
    await set(b, "/retries", 3);
    const read = await get(a, "/max_speed");
    const number = await get(a, "/retries");
    const unset = await get(a, "/never_set");
    const names = await succeeds("getParams", (ok, fail) => a.getParams(ok, fail));
    await succeeds("Param.delete", (ok, fail) =>
      new Param({ ros: b, name: "/retries" }).delete(ok, fail),
    );
    const deleted = await get(a, "/retries");
    return { written: value, read, number, unset, names, deleted };
  },
});
