// Subscribe to a live robot's camera with roslibjs and print the first N frames.
//
//   node camera.mjs URL N   ->   {"frames": [{"stamp": ns, "format": "jpeg", "data": BASE64}, ...]}
//
// The JPEG bytes are handed to the Python test, which decodes them.

import { Ros, Topic } from "roslib";

const [url, count = "3"] = process.argv.slice(2);
const wanted = Number(count);
const deadline = setTimeout(() => {
  console.error(`timed out: fewer than ${wanted} camera frames from ${url}`);
  process.exit(1);
}, 60000);

const ros = new Ros({ url });
ros.on("error", (err) => {
  console.error(`connection error: ${err?.message ?? err}`);
  process.exit(1);
});
const frames = [];
const camera = new Topic({
  ros,
  name: "/camera/image/compressed",
  messageType: "sensor_msgs/msg/CompressedImage",
});
camera.subscribe((message) => {
  const stamp = message.header.stamp.sec * 1e9 + message.header.stamp.nanosec;
  if (frames.length && frames[frames.length - 1].stamp === stamp) return; // the latched one again
  frames.push({ stamp, format: message.format, data: message.data });
  if (frames.length === wanted) {
    clearTimeout(deadline);
    camera.unsubscribe();
    console.log(JSON.stringify({ frames }));
    ros.close();
  }
});
