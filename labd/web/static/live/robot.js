// A live robot's page for a task without a console of its own: who drives, the episode,
// taking control and starting anew, and its camera (lab.js does all of it).

import { $, config, start } from "../page.js";
import { camera, connect } from "./lab.js";

start(async () => {
  const live = await connect(config("live-config"));
  camera(live, $("camera"));
  document.body.dataset.ready = "yes";
});
