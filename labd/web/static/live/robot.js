// A live robot's page for a task without a console of its own: who drives, the episode,
// taking control and starting anew, and its camera (lab.js does all of it).

import { camera, config, connect } from "/static/live/lab.js";

connect(config()).then((live) => {
  camera(live, document.getElementById("camera"));
  document.body.dataset.ready = "yes";
}).catch((err) => {
  document.getElementById("status").textContent = `the page could not start: ${err}`;
  throw err;
});
