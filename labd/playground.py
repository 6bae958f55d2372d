"""The playground's scripts: what the lab commits of one, and whether it parses.

A playground script is a roslibjs program (ESM, for Node.js 20 and the browser alike)
written in ``/playground``. Run as a trial, the lab commits it to the writer's hosted
repository (``labd.hosted``) as a whole controller repository, so that the commit runs,
reruns and can be cloned like any other:

    controller.mjs   the script
    lab.toml         command = ["node", "controller.mjs"], the task
    package.json     ESM, no dependencies (the lab provides roslib; a devDependency on
                     it, so that `npm install` gives it to someone who runs it elsewhere)
    README.md        what this is and how to run it

Before anything is committed the script is parsed with the lab's own Node.js
(``node --check``, which parses and runs nothing); a script that does not parse is a
``ScriptError`` carrying Node's message and where it is (line, column), which the page
shows at that line.

Each task may bring its own starting script (``TaskSpec.playground``); a task without
one starts from a script that watches its observation topics.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import tempfile
import tomllib
from dataclasses import dataclass
from pathlib import Path

from labd.errors import LabError
from labd.sim import registry

SCRIPT = "controller.mjs"
LAB_TOML = "lab.toml"
MAX_SCRIPT = 256 * 1024  # bytes of a script: a controller, not a data file
CHECK_TIMEOUT = 10.0  # seconds Node may take to parse a script
ROSLIB = "2.1.0"  # the roslib the lab provides (sandbox/node/package.json)
WHERE = re.compile(r"^.*:(\d+)$")
MESSAGE = re.compile(r"^(\w*Error)(?: \[\w+\])?: (.*)$")


class PlaygroundError(LabError):
    """The playground cannot take a script (see the subclasses)."""


class ScriptError(PlaygroundError):
    """A script that does not parse: Node's words and where (1-based line and column;
    column 0 when Node does not say)."""

    def __init__(self, message: str, line: int, column: int = 0) -> None:
        self.message = message
        self.line = line
        self.column = column
        where = f"line {line}" + (f", column {column}" if column else "")
        super().__init__(f"{SCRIPT}, {where}: {message}")


class NoNode(PlaygroundError):
    """The lab's machine has no Node.js to parse (or run) a script with."""

    def __init__(self) -> None:
        super().__init__(
            "this lab has no Node.js, so it cannot check or run JavaScript controllers; its"
            " operator installs Node.js 20 or later (docs/trials.md)"
        )


@dataclass(frozen=True)
class Script:
    """A playground script as committed: its text and its task."""

    text: str
    task: str


def template(task: str) -> str:
    """The script ``/playground`` starts from for ``task`` (UnknownTaskError if none)."""
    spec = registry.get(task)
    if spec.playground is not None:
        return spec.playground.read_text(encoding="utf-8")
    observations, _ = spec.topics()
    return _watcher(task, observations)


def _watcher(task: str, observations: list[str]) -> str:
    """A starting script for a task without its own: it reports what each observation
    topic sends, tick by tick in a trial (lockstep), on the robot's clock live."""
    topics = json.dumps([t for t in observations if "image" not in t])
    return f"""\
// {task} from the playground: report the robot's observation topics as they arrive.
// A plain roslibjs program: it reaches the robot at LAB_BRIDGE_URL, in the page and in a
// trial alike. A trial's robot waits for /lab/step (lockstep); a live one runs on its clock.
import {{ Ros, Service, Topic }} from "roslib";

const ros = new Ros({{}});
const connected = new Promise((resolve) => ros.once("connection", resolve));
await ros.connect(process.env.LAB_BRIDGE_URL ?? "ws://127.0.0.1:9090");
await connected;
const services = await new Promise((resolve, reject) => ros.getServices(resolve, reject));
const lockstep = services.includes("/lab/step");
const step = new Service({{ ros, name: "/lab/step", serviceType: "std_srvs/srv/Trigger" }});
const running = (answer) => answer.success && answer.message.endsWith(": running");
const tick = () => lockstep
  ? new Promise((resolve, reject) => step.callService({{}}, (a) => resolve(running(a)), reject))
  : new Promise((resolve) => setTimeout(() => resolve(true), 100));

const types = await new Promise((resolve, reject) => ros.getTopics(resolve, reject));
const seen = new Map();
for (const name of {topics}) {{
  const messageType = types.types[types.topics.indexOf(name)];
  const count = () => seen.set(name, (seen.get(name) ?? 0) + 1);
  if (messageType) new Topic({{ ros, name, messageType }}).subscribe(count);
}}
for (let ticks = 1; await tick(); ticks += 1) {{
  if (ticks % 50 === 0) console.log(`tick ${{ticks}}:`, Object.fromEntries(seen));
  if (!lockstep && ticks >= 300) break;
}}
ros.close();
"""


def files(script: Script, user: str, name: str) -> dict[str, bytes]:
    """The files of a playground repository's commit of ``script``."""
    lab_toml = (
        f"# Written by the lab's playground for {user}: a JavaScript controller (roslibjs).\n"
        "[controller]\n"
        f'command = ["node", "{SCRIPT}"]\n'
        f'task = "{script.task}"\n'
    )
    package = {
        "name": name.lower(),
        "version": "1.0.0",
        "private": True,
        "type": "module",
        "description": f"{user}'s playground script for the lab's {script.task} task",
        "devDependencies": {"roslib": ROSLIB},
    }
    readme = (
        f"# {name}\n\n"
        f"{user}'s script for the lab's `{script.task}` task, written in the lab's playground"
        " and committed by the lab. It is a roslibjs program that reaches the robot at"
        " `LAB_BRIDGE_URL`.\n\n"
        "Run it as the lab does, from a clone of this repository:\n\n"
        "    labd run .\n\n"
        "or against a robot of your own (`labd serve --lockstep`, say):\n\n"
        "    npm install && LAB_BRIDGE_URL=ws://127.0.0.1:9090 node controller.mjs\n"
    )
    return {
        SCRIPT: script.text.encode(),
        LAB_TOML: lab_toml.encode(),
        "package.json": (json.dumps(package, indent=2) + "\n").encode(),
        "README.md": readme.encode(),
    }


def script_of(committed: dict[str, bytes]) -> Script | None:
    """The script of a playground commit's files (None: not a playground repository)."""
    text, toml = committed.get(SCRIPT), committed.get(LAB_TOML)
    if text is None or toml is None:
        return None
    try:
        task = tomllib.loads(toml.decode())["controller"]["task"]
    except (UnicodeDecodeError, tomllib.TOMLDecodeError, KeyError, TypeError):
        return None
    if not isinstance(task, str):
        return None
    return Script(text.decode("utf-8", "replace"), task)


def check(text: str, node: str | None = None) -> None:
    """Parse ``text`` as an ES module with Node.js (nothing runs): ScriptError if it does
    not parse, NoNode if there is no ``node``. Blocking: call it from a thread."""
    if len(text.encode()) > MAX_SCRIPT:
        raise PlaygroundError(
            f"the script is {len(text.encode()) // 1024} KiB; the playground takes scripts of"
            f" at most {MAX_SCRIPT // 1024} KiB (a larger controller belongs in a repository)"
        )
    node = node or shutil.which("node")
    if node is None:
        raise NoNode()
    with tempfile.TemporaryDirectory(prefix="labd-script-") as folder:
        path = Path(folder) / SCRIPT
        path.write_text(text, encoding="utf-8")
        env = {"PATH": os.environ.get("PATH", ""), "NODE_OPTIONS": ""}
        try:
            done = subprocess.run(  # noqa: S603 (the host's node, parsing only)
                [node, "--check", str(path)],
                capture_output=True,
                text=True,
                timeout=CHECK_TIMEOUT,
                env=env,
                cwd=folder,
                check=False,
            )
        except subprocess.TimeoutExpired:
            raise PlaygroundError(
                f"Node.js took more than {CHECK_TIMEOUT:g} s to parse the script; shorten it"
            ) from None
    if done.returncode == 0:
        return
    raise _parse_failure(done.stderr, text.count("\n") + 1)


def _parse_failure(stderr: str, lines: int) -> ScriptError:
    """Node's ``--check`` report (``FILE:LINE``, the line, a caret, ``SyntaxError: ...``)
    as a ScriptError at its line (at most the script's last) and column."""
    report = stderr.splitlines()
    line, column, message = 0, 0, ""
    for n, text in enumerate(report):
        if not line and (where := WHERE.match(text)):
            line = int(where.group(1))
            caret = report[n + 2] if n + 2 < len(report) else ""
            if caret.strip() and set(caret.strip()) == {"^"}:
                column = len(caret) - len(caret.lstrip()) + 1
        if not message and (said := MESSAGE.match(text.strip())):
            message = f"{said.group(1)}: {said.group(2)}"
    return ScriptError(message or "the script does not parse", min(max(line, 1), lines), column)
