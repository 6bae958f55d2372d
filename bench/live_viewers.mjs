// Camera viewers for bench/live.py: N roslibjs clients (npm roslib 2.x, from
// tests/js/node_modules) in this one Node process, each subscribed to a live robot's
// camera for some seconds. Prints one JSON line: the frames each received.
//   node bench/live_viewers.mjs URL N SECONDS
import { dirname, join } from "node:path";
import { fileURLToPath, pathToFileURL } from "node:url";

const here = dirname(fileURLToPath(import.meta.url));
const roslib = join(here, "..", "tests", "js", "node_modules", "roslib", "dist", "RosLib.js");
const { Ros, Topic } = await import(pathToFileURL(roslib).href);
const [url, n, seconds] = [process.argv[2], Number(process.argv[3]), Number(process.argv[4])];

const viewers = await Promise.all(Array.from({ length: n }, async () => {
  const ros = new Ros({});
  const opened = new Promise((resolve, reject) => { ros.on("connection", resolve); ros.on("error", reject); });
  await ros.connect(url);
  await opened;
  const viewer = { ros, frames: 0, bytes: 0, started: 0 };
  new Topic({ ros, name: "/camera/image/compressed", messageType: "sensor_msgs/msg/CompressedImage", queue_length: 1 })
    .subscribe((m) => {
      if (!viewer.started) viewer.started = performance.now();  // count from the first frame
      else { viewer.frames += 1; viewer.bytes += m.data.length; }
    });
  return viewer;
}));
process.stdout.write("ready\n");
await new Promise((resolve) => setTimeout(resolve, seconds * 1000));
const now = performance.now();
const fps = viewers.map((v) => (v.started ? v.frames / ((now - v.started) / 1000) : 0));
for (const v of viewers) v.ros.close();
process.stdout.write(JSON.stringify({ fps }) + "\n");
process.exit(0);
