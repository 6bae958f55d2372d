// The playground page (labd/web/playground.py): a CodeMirror editor holding a roslibjs
// script, and two ways to run it.
//
// - Run live: the script runs in a frame of this page (/playground/runner, sandboxed: an
//   opaque origin that reaches only the robot's bridge), connected to the chosen live
//   robot with the person's slot key when the lab takes reservations. Whatever it prints
//   is shown beside the robot's camera; Stop removes the frame, and with it the script's
//   connection (its drive ends, and is filed like any drive).
// - Run as a trial: the lab parses the script (its errors are shown at their line, and
//   nothing is committed), commits it to the person's repository and queues a trial of
//   that commit (POST /api/playground/trials); the page links to the trial.
//
// The script is kept in the browser's storage per task between visits, until it is run
// as a trial or started again. The checks and the runner's messages are in checks.js.

import {
  EditorView, basicSetup, javascript, lintGutter, parse, setDiagnostics,
} from "/static/vendor/codemirror/codemirror.min.js";
import { Ros } from "/static/vendor/roslib/roslib.min.js";
import { camera, slotKey } from "../live/lab.js";
import { $, config, count, status } from "../page.js";
import { bridgeAddress, fromRunner, markRange, syntaxError, trialProgress } from "./checks.js";

const cfg = config("playground-config");
const csrf = document.querySelector("meta[name=csrf-token]")?.content ?? "";
const stored = `labd.playground.${cfg.task}`;
const MAX_LINES = 2000; // of the console; older lines are dropped

// -- the editor ---------------------------------------------------------------------------
const initial = cfg.opened?.script ?? localStorage.getItem(stored) ?? cfg.template;
const editor = new EditorView({
  doc: initial,
  extensions: [
    EditorView.cspNonce.of($("editor").dataset.nonce), // its styles, under the page's policy
    basicSetup,
    EditorView.lineWrapping,
    javascript(),
    lintGutter(),
    EditorView.updateListener.of((update) => {
      if (!update.docChanged) return;
      localStorage.setItem(stored, update.state.doc.toString());
      editor.dispatch(setDiagnostics(update.state, [])); // an old mark no longer says anything
    }),
  ],
  parent: $("editor"),
});
window.labPlayground = { editor, cfg };
const script = () => editor.state.doc.toString();

/** Mark the script's line ``line`` (1-based; column 0 = the whole line) with ``message``. */
function mark(message, line, column = 0) {
  const { from, to } = markRange(editor.state.doc, line, column);
  editor.dispatch(setDiagnostics(editor.state, [{ from, to, severity: "error", message }]));
  editor.dispatch({ selection: { anchor: from }, scrollIntoView: true });
}

$("reset-script").addEventListener("click", () => {
  editor.dispatch({ changes: { from: 0, to: editor.state.doc.length, insert: cfg.template } });
  localStorage.removeItem(stored);
});
$("task").addEventListener("change", (event) => event.target.form.submit());

// -- the console --------------------------------------------------------------------------
function print(text, level = "log") {
  const line = document.createElement("div");
  line.className = `pg-${level}`;
  line.textContent = text;
  const box = $("console");
  box.append(line);
  while (box.childElementCount > MAX_LINES) box.firstElementChild.remove();
  box.scrollTop = box.scrollHeight;
  count(box, "lines");
}

// -- the robot's camera (the page watches with its own connection) -------------------------
let viewer = null;
async function key(robot) {
  if (!cfg.reservations) return null;
  if (!cfg.signed_in) throw new Error("this lab's robots are driven in reserved slots: sign in, and book one on /reservations");
  return (await slotKey(robot, "no slot of yours on this robot runs now: book one on /reservations")).key;
}
const address = (robot, slot) => bridgeAddress(cfg.robots, robot, slot);
async function watch(robot) {
  if (viewer) viewer.close();
  viewer = null;
  if (!robot) return;
  let slot = null;
  if (cfg.signed_in) slot = await key(robot).catch(() => null); // else watch, if the lab lets anyone
  const ros = new Ros({});
  ros.on("error", () => status(`cannot reach ${robot}'s bridge`, "warning"));
  await ros.connect(address(robot, slot));
  viewer = ros;
  camera({ ros, ux: () => {} }, $("camera"));
}
const robotChoice = () => (cfg.robots.length ? $("robot").value : null);
$("robot").addEventListener("change", () => watch(robotChoice()));
watch(robotChoice()).catch((err) => status(String(err), "warning"));

// -- Run live -----------------------------------------------------------------------------
let frame = null;
function stop(why) {
  if (frame) {
    frame.remove();
    frame = null;
    window.removeEventListener("message", heard);
  }
  $("run-live").disabled = !cfg.robots.length;
  $("stop").disabled = true;
  document.body.dataset.running = "no";
  if (why) status(why);
}
function heard(event) {
  if (!frame || event.source !== frame.contentWindow) return;
  const said = fromRunner(event.data);
  if (said?.do === "run") {
    frame.contentWindow.postMessage({ op: "run", code: script(), url: frame.dataset.url }, "*");
    status(`running live on ${frame.dataset.robot}`);
  } else if (said?.do === "print") {
    print(said.text, said.level);
  } else if (said?.do === "fail") {
    print(said.printed, "error");
    if (said.mark) mark(said.mark.message, said.mark.line, said.mark.column);
    stop(said.why);
    $("status").dataset.level = "error";
  } else if (said?.do === "stop") {
    stop(said.why);
  }
}
/** Whether the script parses (acorn, as an ES module); if not, its error is marked. */
function parses() {
  const error = syntaxError(parse, script());
  if (error === null) return true;
  mark(error.message, error.line, error.column);
  status(`line ${error.line}: ${error.message}`, "error");
  return false;
}
$("run-live").addEventListener("click", async () => {
  const robot = robotChoice();
  if (!robot) return;
  stop();
  $("console").replaceChildren();
  if (!parses()) return;
  let slot;
  try {
    slot = await key(robot);
  } catch (err) {
    status(err.message, "warning");
    return;
  }
  frame = document.createElement("iframe");
  frame.sandbox = "allow-scripts"; // an opaque origin: the bridge, and nothing of yours
  frame.className = "pg-runner";
  frame.title = "the script, running";
  frame.dataset.url = address(robot, slot);
  frame.dataset.robot = robot;
  window.addEventListener("message", heard);
  frame.src = "/playground/runner";
  document.body.append(frame);
  $("run-live").disabled = true;
  $("stop").disabled = false;
  document.body.dataset.running = "yes";
  status("starting…");
});
$("stop").addEventListener("click", () => stop("stopped: the script's connection is closed"));

// -- Run as a trial -----------------------------------------------------------------------
async function post(path, body) {
  const answer = await fetch(path, {
    method: "POST",
    credentials: "same-origin",
    headers: { "Content-Type": "application/json", "X-CSRF-Token": csrf },
    body: JSON.stringify(body),
  });
  const said = await answer.json().catch(() => ({ error: `the lab answered ${answer.status}` }));
  if (!answer.ok) throw new Error(said.error || `the lab answered ${answer.status}`);
  return said;
}
/** Show the trial's progress until it ends: queued, running, then its outcome and why. */
async function follow(trial) {
  for (;;) {
    const progress = trialProgress(trial);
    status(progress.text, progress.level);
    if (progress.ended) break;
    await new Promise((resolve) => setTimeout(resolve, 2000));
    const answer = await fetch(`/api/trials/${trial.id}`, { credentials: "same-origin" });
    if (!answer.ok) break;
    trial = await answer.json();
  }
  $("result").dataset.ended = trial.status;
}
/** Parse the script with the lab's Node.js; false (its error marked) if it does not. */
async function parsedByTheLab() {
  status("parsing the script…");
  const parsed = await post("/api/playground/check", { script: script() });
  if (parsed.ok) return true;
  mark(parsed.error, parsed.line, parsed.column);
  status(`line ${parsed.line}: ${parsed.error} (nothing was committed)`, "error");
  return false;
}
function link(href, text, id) {
  return Object.assign(document.createElement("a"), { href, textContent: text, id });
}
/** After a commit: the script is in the repository; the page's address names it. */
function committed(run, what) {
  localStorage.removeItem(stored);
  const result = $("result");
  result.replaceChildren(
    ...what, ` of commit ${run.commit.slice(0, 12)} · `,
    Object.assign(document.createElement("code"), { textContent: `git clone ${run.repository}` }),
  );
  result.dataset.commit = run.commit;
  const page = new URL(run.playground);
  history.replaceState(null, "", page.pathname + page.search);
}
/** ``work()`` with the writing buttons off, its failure shown. */
async function writing(work) {
  const buttons = [$("run-trial"), $("evaluate")].filter(Boolean);
  buttons.forEach((b) => { b.disabled = true; });
  try {
    if (await parsedByTheLab()) await work();
  } catch (err) {
    status(err.message, "error");
  } finally {
    buttons.forEach((b) => { b.disabled = false; });
  }
}
const asked = () => ({ name: $("name").value, task: cfg.task, script: script() });
$("run-trial")?.addEventListener("click", () => writing(async () => {
  status("committing and queueing…");
  const run = await post("/api/playground/trials", { ...asked(), seed: Number($("seed").value || 0) });
  const t = run.trial;
  committed(run, ["Trial ", link(`/trials/${t.id}`, `#${t.id}`, "trial-link")]);
  $("result").dataset.trial = String(t.id);
  await follow(t);
}));
$("evaluate")?.addEventListener("click", () => writing(async () => {
  status("committing and queueing every episode…");
  const made = await post("/api/playground/evaluations", { ...asked(), suite: $("suite").value });
  const e = made.evaluation;
  committed(made, ["Evaluation ", link(`/evaluations/${e.id}`, `#${e.id}`, "evaluation-link"), ` on ${e.suite}`]);
  $("result").dataset.evaluation = String(e.id);
  status(`evaluation #${e.id} queued: ${e.rows.length} episodes`);
}));
document.body.dataset.ready = "yes";
