// Camera viewers for bench/live.py, over Foxglove's protocol: N FoxgloveClients (npm
// @foxglove/ws-protocol 0.8, offering foxglove.sdk.v1, from tests/js/node_modules) in this
// one Node process, each subscribed to a live robot's camera for some seconds. One frame
// in ten is decoded with Foxglove's ROS 2 reader (@foxglove/rosmsg2-serialization), as the
// app would, and checked to be a JPEG. Prints one JSON line: the frames each received.
//   node bench/live_foxglove_viewers.mjs URL N SECONDS
import { createRequire } from "node:module";
import { dirname, join } from "node:path";
import { fileURLToPath } from "node:url";

// The packages live in tests/js/node_modules, which an import from bench/ does not search.
const here = dirname(fileURLToPath(import.meta.url));
const require = createRequire(join(here, "..", "tests", "js", "package.json"));
const { FoxgloveClient } = require("@foxglove/ws-protocol");
const { MessageReader } = require("@foxglove/rosmsg2-serialization");
const { parse } = require("@foxglove/rosmsg");
const WebSocket = require("ws");

const TOPIC = "/camera/image/compressed";
const [url, n, seconds] = [process.argv[2], Number(process.argv[3]), Number(process.argv[4])];

const viewers = await Promise.all(Array.from({ length: n }, async () => {
  const ws = new WebSocket(url, ["foxglove.sdk.v1"]);
  const client = new FoxgloveClient({ ws });
  const viewer = { client, frames: 0, bytes: 0, started: 0, checked: 0, jpegs: 0, errors: [] };
  client.on("error", (err) => viewer.errors.push(String(err?.message ?? err)));
  const subscribed = new Promise((resolve, reject) => {
    ws.once("error", reject);
    client.on("advertise", (channels) => {
      const camera = channels.find((c) => c.topic === TOPIC);
      if (!camera || viewer.sub !== undefined) return;
      const reader = new MessageReader(parse(camera.schema, { ros2: true }));
      viewer.sub = client.subscribe(camera.id);
      client.on("message", ({ subscriptionId, data }) => {
        if (subscriptionId !== viewer.sub) return;
        if (!viewer.started) viewer.started = performance.now();  // count from the first frame
        else { viewer.frames += 1; viewer.bytes += data.byteLength; }
        if ((viewer.frames % 10) === 0) {
          const image = reader.readMessage(data);
          viewer.checked += 1;
          const d = image.data;
          if (image.format.includes("jpeg") && d[0] === 0xff && d[1] === 0xd8 && d[2] === 0xff) {
            viewer.jpegs += 1;
          }
        }
      });
      resolve();
    });
  });
  await subscribed;
  return viewer;
}));
process.stdout.write("ready\n");
await new Promise((resolve) => setTimeout(resolve, seconds * 1000));
const now = performance.now();
const fps = viewers.map((v) => (v.started ? v.frames / ((now - v.started) / 1000) : 0));
const checked = viewers.reduce((sum, v) => sum + v.checked, 0);
const jpegs = viewers.reduce((sum, v) => sum + v.jpegs, 0);
const errors = viewers.flatMap((v) => v.errors);
for (const v of viewers) v.client.close();
process.stdout.write(JSON.stringify({ fps, checked, jpegs, errors }) + "\n");
process.exit(0);
