#!/usr/bin/env python3
"""The deployment's smoke test: deploy/'s compose stack, used as a team would use it.

    .venv/bin/python deploy/smoke.py [--no-build] [--keep] [--ray]    (make deploy-smoke)

(``--ray``: the stack on its Ray cluster, deploy/docker-compose.ray.yml: a trial, an
evaluation over both nodes with most replays on the other node, a rerun.)

1. builds the images (``deploy/build_image.py``; ``--no-build`` takes ``labd:VERSION`` and
   ``labd-postgres:VERSION`` as they are);
2. puts the example controller ``controllers/examples/icreate-maze`` in a git repository
   served by ``git daemon`` (``deploy/smoke.yml`` adds that service to the stack);
3. brings the stack up with docker-compose under a project name of its own, on free
   host ports, and waits until ``/readyz`` counts two remote workers;
4. adds a user with ``labd users add`` inside the lab's container (the command reads the
   lab's configuration, no flag needed), then from this machine, through the published
   port: submits the example (``labd submit --wait``: success), runs a playground script
   as a trial (committed to the lab's hosted repository under its public URL, the host's
   port, and run by a remote worker, which reaches the lab as ``http://lab:8080``),
   evaluates the example on the maze's ``dev`` suite (``labd evaluate --wait``: every
   episode succeeds, both workers run some, every replay verifies), reruns the trial
   (reproduced), downloads its record and verifies it against the lab's keys
   (``labd verify``), and reads ``/metrics``;
5. backs the lab up while it runs into a host folder, removes the stack and its volumes,
   restores a new stack from the backup as docs/operate.md says, and checks that it
   serves the same trials and the same record, which still verifies;
6. tears the stack down, volumes and all (``--keep`` leaves it up and prints how to end it).

Each step prints a line as it starts and ends; the first failure stops the test (exit 1)
with what was expected and what came, after printing the lab's and the workers' logs.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
import urllib.error
import urllib.request
from collections.abc import Callable
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parent.parent
DEPLOY = REPO / "deploy"
LABD = Path(sys.executable).parent / "labd"  # the CLI of the venv that runs this test
EXAMPLE = REPO / "controllers" / "examples" / "icreate-maze"
EXAMPLE_URL = "git://git/icreate-maze.git"  # as the lab and the workers reach it
LAB_UID = 10001  # the lab's user in the image (deploy/build_image.py)
UP_TIMEOUT = 300.0  # seconds for the stack to be ready (first start: PostgreSQL's initdb)
STARTED = time.monotonic()


class SmokeError(Exception):
    """A step did not do what it should; the message says what was expected."""


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--no-build", action="store_true", help="use the images as they are")
    parser.add_argument("--keep", action="store_true", help="leave the stack up at the end")
    parser.add_argument(
        "--ray",
        action="store_true",
        help="the stack on a Ray cluster (deploy/docker-compose.ray.yml): a trial, an"
        " evaluation over both nodes, a rerun",
    )
    args = parser.parse_args()
    work = Path(tempfile.mkdtemp(prefix="labd-smoke-"))
    stack = Stack(f"labd-smoke-{os.getpid()}", work, ray=args.ray)
    try:
        version = build() if not args.no_build else _version()
        stack.env["LABD_VERSION"] = version
        example_repository(work / "git")
        stack.up()
        if args.ray:
            run_the_cluster(stack)
        else:
            run_the_lab(stack, work)
    except SmokeError as err:
        stack.logs()
        say(f"FAILED: {err}")
        return 1
    finally:
        if args.keep:
            say(
                f"left up; to end it: SMOKE_GIT={stack.env['SMOKE_GIT']} docker-compose"
                f" -p {stack.project} {' '.join(stack.files)} down -v"
            )
        else:
            stack.down()
            shutil.rmtree(work, ignore_errors=True)
    say("passed")
    return 0


def build() -> str:
    step("building the images (deploy/build_image.py)")
    done = subprocess.run(  # noqa: S603 - our own script
        [sys.executable, str(DEPLOY / "build_image.py")],
        stdout=subprocess.PIPE,
        text=True,
        check=False,
    )
    if done.returncode != 0:
        raise SmokeError(f"deploy/build_image.py failed ({done.returncode})")
    tags = done.stdout.split()
    say(f"built {', '.join(tags)}")
    return tags[0].split(":", 1)[1]


def example_repository(root: Path) -> None:
    """The example controller as a bare repository under ``root``, branch main."""
    step(f"the example {EXAMPLE.relative_to(REPO)} as a git repository ({EXAMPLE_URL})")
    tree = root.parent / "icreate-maze"
    shutil.copytree(EXAMPLE, tree, ignore=shutil.ignore_patterns("__pycache__"))
    git = ["git", "-c", "user.name=smoke", "-c", "user.email=smoke@labd.invalid"]
    _run([*git, "init", "-q", "-b", "main", str(tree)])
    _run([*git, "-C", str(tree), "add", "-A"])
    _run([*git, "-C", str(tree), "commit", "-q", "-m", "the example maze controller"])
    _run(["git", "clone", "-q", "--bare", str(tree), str(root / "icreate-maze.git")])


class Stack:
    """deploy/docker-compose.yml (with deploy/smoke.yml) under a project name of its own."""

    def __init__(self, project: str, work: Path, *, ray: bool = False) -> None:
        self.project = project
        self.ray = ray
        self.files = ["-f", str(DEPLOY / "docker-compose.yml"), "-f", str(DEPLOY / "smoke.yml")]
        if ray:
            self.files += ["-f", str(DEPLOY / "docker-compose.ray.yml")]
        http, bridge = free_ports(2)
        self.server = f"http://127.0.0.1:{http}"
        self.env = {
            **os.environ,
            "HTTP_PORT": str(http),
            "BRIDGE_PORT": str(bridge),
            "PUBLIC_URL": self.server,
            "SMOKE_GIT": str(work / "git"),
        }
        if ray:
            self.env["RAY_AUTH_TOKEN"] = os.urandom(32).hex()
        self.started = False

    def compose(self, *command: str, check: bool = True) -> str:
        argv = ["docker-compose", "-p", self.project, *self.files, *command]
        done = subprocess.run(  # noqa: S603 - docker-compose on our own files
            argv, env=self.env, capture_output=True, text=True, check=False
        )
        if check and done.returncode != 0:
            raise SmokeError(
                f"docker-compose {' '.join(command)} failed ({done.returncode}):"
                f" {_tail(done.stderr or done.stdout)}"
            )
        return done.stdout

    def up(self) -> None:
        step(f"docker-compose up ({self.project}; HTTP on {self.server})")
        self.started = True
        self.compose("up", "-d")
        say("containers: " + " ".join(sorted(self.compose("ps", "--services").split())))
        what = "two Ray nodes" if self.ray else "both workers"
        step(f"waiting for the lab to be ready with {what} (/readyz)")
        ready = wait_for(self.readiness, UP_TIMEOUT, f"the lab ready with {what}")
        say(f"ready: {ready}")

    def readiness(self) -> str | None:
        try:
            with urllib.request.urlopen(f"{self.server}/readyz", timeout=5) as answer:  # noqa: S310
                body = json.load(answer)
        except (OSError, ValueError):
            return None  # not listening yet, or not ready (503)
        checks = body.get("checks", {})
        if self.ray:
            return json.dumps(checks) if "2 node(s)" in str(checks.get("cluster", "")) else None
        return json.dumps(checks) if "2 remote" in str(checks.get("workers", "")) else None

    def database_ready(self) -> str | None:
        ready = ["exec", "-T", "postgres", "pg_isready", "-q", "-h", "127.0.0.1", "-U", "labd"]
        argv = ["docker-compose", "-p", self.project, *self.files, *ready]
        done = subprocess.run(argv, env=self.env, capture_output=True, check=False)  # noqa: S603
        return "ready" if done.returncode == 0 else None

    def logs(self) -> None:
        if self.started:
            print(self.compose("logs", "--no-color", "--tail", "60", check=False), flush=True)

    def down(self) -> None:
        if self.started:
            step("docker-compose down -v (containers, network, volumes)")
            self.compose("down", "-v", "--remove-orphans", check=False)
            say("the stack is gone")


def run_the_lab(stack: Stack, work: Path) -> None:
    token, env = smoke_user(stack)

    step(f"labd submit {EXAMPLE_URL} --ref main --wait")
    trial = labd(env, "submit", EXAMPLE_URL, "--ref", "main", "--wait")
    expect(trial.get("outcome") == "success", "the example to succeed", trial)
    say(f"trial {trial['id']}: {trial['outcome']} ({trial.get('reason')})")

    playground_trial(stack, token)

    step("labd evaluate --suite dev --wait (the maze's 20 public episodes, on two workers)")
    evaluation = evaluate_dev(env)
    workers = set()
    for row in evaluation["rows"]:
        detail = json.loads(http_get(f"{stack.server}/api/trials/{row['trial']}"))
        workers.add(str(detail.get("worker")).split("/")[0])
    expect(len(workers) == 2, "episodes run by both workers", sorted(workers))
    say(
        f"evaluation {evaluation['id']}: {evaluation['successes']} of {evaluation['episodes']}"
        f" succeeded, every replay verified; run by {len(workers)} workers"
    )

    step(f"labd rerun {trial['id']} --wait")
    reruns = labd(env, "rerun", str(trial["id"]), "--wait")
    expect(len(reruns) == 1 and reruns[0].get("reproduced") is True, "reproduced", reruns)
    say(f"rerun of trial {trial['id']}: reproduced")

    step(f"labd download {trial['id']}, then labd verify against /api/keys")
    record = work / f"trial-{trial['id']}.mcap"
    labd(env, "download", str(trial["id"]), "-o", str(record))
    keys = work / "lab-keys.json"
    keys.write_bytes(http_get(f"{stack.server}/api/keys"))
    verified = labd(env, "verify", str(record), "--key", str(keys))
    say(f"{record.name} ({record.stat().st_size} bytes): {json.dumps(verified)[:200]}")

    step("/metrics")
    metrics = http_get(f"{stack.server}/metrics").decode()
    finished = [line for line in metrics.splitlines() if line.startswith("labd_trials")]
    expect(bool(finished), "labd_trials* series in /metrics", metrics[:500])
    say(f"{len(metrics.splitlines())} lines, for example {finished[0]}")

    back_up_and_restore(stack, work, env, trial, record)


def smoke_user(stack: Stack) -> tuple[str, dict[str, str]]:
    """The user ``smoke``, added in the lab's container: its token, and the environment
    the ``labd`` commands below run in (a developer's own settings kept out of it)."""
    step("labd users add smoke (in the lab's container, reading its configuration)")
    added = json.loads(
        stack.compose("exec", "-T", "lab", "labd", "users", "add", "smoke", "--json")
    )
    env = {**os.environ, "LABD_SERVER": stack.server, "LABD_TOKEN": added["token"]}
    for name in [
        k for k in env if k.startswith("LABD_") and k not in ("LABD_SERVER", "LABD_TOKEN")
    ]:
        del env[name]
    return str(added["token"]), env


def evaluate_dev(env: dict[str, str]) -> dict[str, Any]:
    """The example evaluated on the maze's dev suite, to its end: every episode a
    success, every replay verified."""
    evaluation: dict[str, Any] = labd(
        env, "evaluate", EXAMPLE_URL, "--ref", "main", "--suite", "dev", "--wait"
    )
    expect(evaluation.get("status") == "finished", "the evaluation finished", evaluation)
    expect(
        evaluation.get("successes") == evaluation.get("episodes"),
        "every episode a success",
        evaluation,
    )
    expect(evaluation.get("verified") is True, "every episode's replay verified", evaluation)
    return evaluation


def run_the_cluster(stack: Stack) -> None:
    """The lab on its Ray cluster: a trial and an evaluation run by the nodes, each record
    replayed on the other node, a rerun reproduced."""
    _, env = smoke_user(stack)

    step(f"labd submit {EXAMPLE_URL} --ref main --wait (on a node of the cluster)")
    trial = labd(env, "submit", EXAMPLE_URL, "--ref", "main", "--wait")
    expect(trial.get("outcome") == "success", "the example to succeed", trial)
    expect(str(trial.get("worker")).startswith("ray:"), "a node of the cluster ran it", trial)
    say(f"trial {trial['id']}: {trial['outcome']}, run by {trial['worker']}")

    step("labd evaluate --suite dev --wait (20 episodes over the two nodes)")
    evaluation = evaluate_dev(env)
    nodes = set()
    for row in evaluation["rows"]:
        detail = json.loads(http_get(f"{stack.server}/api/trials/{row['trial']}"))
        nodes.add(str(detail.get("worker")))
    expect(
        len(nodes) == 2 and all(n.startswith("ray:") for n in nodes), "both nodes ran some", nodes
    )
    elsewhere = evaluation.get("verified_elsewhere") or 0
    expect(elsewhere * 2 > evaluation["episodes"], "most replays on the other node", evaluation)
    say(
        f"evaluation {evaluation['id']}: {evaluation['successes']} of {evaluation['episodes']}"
        f" succeeded on {len(nodes)} nodes; verified on another machine: {elsewhere}"
    )

    step(f"labd rerun {trial['id']} --wait")
    reruns = labd(env, "rerun", str(trial["id"]), "--wait")
    expect(len(reruns) == 1 and reruns[0].get("reproduced") is True, "reproduced", reruns)
    say(f"rerun of trial {trial['id']}: reproduced, by {reruns[0].get('worker')}")


def playground_trial(stack: Stack, token: str) -> None:
    """The maze's playground script, cut to 40 ticks, run as a trial: the lab commits it
    to its hosted repository, recorded under the public URL (the host's port, which
    leads nowhere inside the containers), and a remote worker fetches it from its own
    ``--server`` (``http://lab:8080``) and runs it to its end."""
    step("a playground script as a trial (POST /api/playground/trials), on a remote worker")
    sys.path.insert(0, str(REPO))
    from labd.playground import template  # noqa: PLC0415 - this checkout's

    script = template("icreate-maze")
    loop = "  if (!(await tick())) break;"
    expect(loop in script, "the maze's playground script to step in a loop", script[:1500])
    short = "let ticks = 0;\n" + script.replace(
        loop, "  if (!(await tick()) || ++ticks >= 40) break;"
    )
    body = {"name": "smoke", "task": "icreate-maze", "script": short}
    made = http_post(f"{stack.server}/api/playground/trials", body, token)
    repository = f"{stack.server}/git/smoke/smoke.git"
    expect(made.get("repository") == repository, f"the repository {repository}", made)
    url = f"{stack.server}/api/trials/{made['trial']['id']}"

    def ended() -> str | None:
        text = http_get(url).decode()
        return text if json.loads(text)["status"] in ("finished", "cancelled") else None

    trial = json.loads(wait_for(ended, 300, "end of the playground trial"))
    expect(trial["outcome"] == "fail", "the script to run its 40 ticks (outcome fail)", trial)
    expect("before the episode ended" in trial["reason"], "it left after 40 ticks", trial)
    expect(str(trial["worker"]).startswith("worker-"), "a remote worker ran it", trial)
    expect(trial["repository"] == repository, f"the repository {repository}", trial)
    say(
        f"trial {trial['id']} of {repository}@{trial['commit'][:12]}: {trial['outcome']}"
        f" ({trial['reason']}), run by {trial['worker']}"
    )


def back_up_and_restore(
    stack: Stack, work: Path, env: dict[str, str], trial: dict[str, Any], record: Path
) -> None:
    """docs/operate.md's backup and restore, word for word: a backup into a host folder
    while the lab runs; the stack and its volumes removed; a new stack restored from it
    before its first start; the same trials, the same record, still verifying."""
    backups = work / "backups"
    backups.mkdir()
    os.chown(backups, LAB_UID, -1)
    mount = ["-v", f"{backups}:/backups"]
    before = labd(env, "trials", "--limit", "500")["trials"]
    step("labd backup /backups/lab (docker-compose run, while the lab runs)")
    made = stack.compose(
        "run", "--rm", "--no-deps", *mount, "lab", "labd", "backup", "/backups/lab", "--json"
    )
    say(f"backup: {_last_json(made)}")

    step("docker-compose down -v: the lab, its database, store and volumes are gone")
    stack.compose("down", "-v", "--remove-orphans")
    step("a new stack restored from the backup before its first start")
    stack.compose("up", "-d", "postgres", "s3")
    wait_for(stack.database_ready, UP_TIMEOUT, "PostgreSQL of the new stack")
    stack.compose(
        "run",
        "--rm",
        "--no-deps",
        "setup",
        "labd-setup",
        "--config",
        "/etc/labd/labd.toml",
        "--create-bucket",
    )
    restored = stack.compose(
        "run", "--rm", "--no-deps", *mount, "lab", "labd", "restore", "/backups/lab", "--json"
    )
    say(f"restore: {_last_json(restored)}")
    stack.up()
    after = labd(env, "trials", "--limit", "500")["trials"]
    same = [(t["id"], t["outcome"]) for t in after] == [(t["id"], t["outcome"]) for t in before]
    expect(same, f"the same {len(before)} trials after the restore", after[:5])
    again = work / f"restored-{trial['id']}.mcap"
    labd(env, "download", str(trial["id"]), "-o", str(again))
    expect(again.read_bytes() == record.read_bytes(), "the same record, byte for byte", str(again))
    keys = work / "restored-keys.json"
    keys.write_bytes(http_get(f"{stack.server}/api/keys"))
    labd(env, "verify", str(again), "--key", str(keys))
    say(f"restored: {len(after)} trials as before; trial {trial['id']}'s record the same, verified")


def labd(env: dict[str, str], *command: str) -> Any:
    """``labd COMMAND --json`` on this machine; its answer, which must be no error."""
    done = subprocess.run(  # noqa: S603 - the venv's own labd
        [str(LABD), *command, "--json"], env=env, capture_output=True, text=True, check=False
    )
    try:
        answer = json.loads(done.stdout)
    except ValueError:
        answer = None
    if done.returncode != 0 or answer is None or (isinstance(answer, dict) and "error" in answer):
        said = answer.get("error") or answer.get("reason") if isinstance(answer, dict) else None
        raise SmokeError(
            f"labd {' '.join(command)} exited {done.returncode}:"
            f" {said or done.stdout.strip()[-1500:]} {_tail(done.stderr)}"
        )
    return answer


def http_get(url: str) -> bytes:
    try:
        with urllib.request.urlopen(url, timeout=30) as answer:  # noqa: S310 - our own lab
            return bytes(answer.read())
    except (OSError, urllib.error.HTTPError) as err:
        raise SmokeError(f"GET {url}: {err}") from None


def http_post(url: str, body: dict[str, Any], token: str) -> Any:
    """POST ``body`` as JSON with the token; the JSON answer, which must be a 2xx."""
    request = urllib.request.Request(  # noqa: S310 - our own lab
        url,
        data=json.dumps(body).encode(),
        method="POST",
        headers={"Authorization": f"Bearer {token}", "Content-Type": "application/json"},
    )
    try:
        with urllib.request.urlopen(request, timeout=120) as answer:  # noqa: S310
            return json.load(answer)
    except urllib.error.HTTPError as err:
        raise SmokeError(f"POST {url}: {err.code} {err.read().decode()[:1500]}") from None
    except OSError as err:
        raise SmokeError(f"POST {url}: {err}") from None


def wait_for(probe: Callable[[], str | None], timeout: float, what: str) -> str:
    """Ask ``probe`` every second until it answers, for at most ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        found = probe()
        if found is not None:
            return found
        time.sleep(1)
    raise SmokeError(f"no {what} within {timeout:.0f} s")


def expect(holds: bool, what: str, got: object) -> None:
    if not holds:
        raise SmokeError(f"expected {what}; got {json.dumps(got, default=str)[:1500]}")


def free_ports(count: int) -> list[int]:
    """Ports free on this host now (held open together, so they differ)."""
    sockets = []
    try:
        for _ in range(count):
            s = socket.socket()
            s.bind(("127.0.0.1", 0))
            sockets.append(s)
        return [s.getsockname()[1] for s in sockets]
    finally:
        for s in sockets:
            s.close()


def _version() -> str:
    sys.path.insert(0, str(REPO))
    import labd  # noqa: PLC0415 - this checkout's

    return labd.__version__


def _run(command: list[str]) -> None:
    done = subprocess.run(command, capture_output=True, text=True, check=False)  # noqa: S603
    if done.returncode != 0:
        raise SmokeError(f"{' '.join(command)} failed: {_tail(done.stderr)}")


def _last_json(text: str) -> str:
    """The JSON object a ``--json`` command printed last (compose adds lines of its own)."""
    lines = text.strip().splitlines()
    for start in reversed([n for n, line in enumerate(lines) if line.startswith("{")]):
        try:
            return json.dumps(json.loads("\n".join(lines[start:])))[:300]
        except ValueError:
            continue
    return text.strip()[-300:]


def _tail(text: str, lines: int = 20) -> str:
    return "\n".join(text.strip().splitlines()[-lines:])


def step(message: str) -> None:
    say(f"-- {message}")


def say(message: str) -> None:
    print(f"[smoke {time.monotonic() - STARTED:6.1f} s] {message}", flush=True)


if __name__ == "__main__":
    sys.exit(main())
