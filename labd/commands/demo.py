"""``labd demo``: the lab, end to end, on this machine (what ``make demo`` runs).

1. The example controllers (``controllers/examples/*``) are made into git repositories
   under ``DATA/demo/``, as a user's would be.
2. A user ``demo`` is made; its token is kept in ``DATA/demo/token`` for later runs.
3. ``labd serve`` starts (the bridge, the robots, the HTTP API, one worker), on the
   default ports if they are free and on free ones if not (or on those given), with
   ``--allow-local-repos`` (the examples are local repositories), and the lab's address
   and the token go into ``DATA/demo/env``, a file to ``source``.
4. Each example is submitted by its repository's path and branch, like any other
   repository, and the demo waits for the trials to end and prints their outcomes.
5. It prints where to look and what to try, every command as it works once the env
   file is sourced, and keeps the lab running until Ctrl-C.
"""

from __future__ import annotations

import argparse
import os
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from labd import datalock
from labd.api.models import TrialDetail
from labd.commands import settings
from labd.commands.common import ExitCode, exit_code, worst
from labd.commands.remote import headline, wait
from labd.config import BridgeConfig
from labd.lab import LabConfig
from labd.service import ServiceConfig
from labd.trial import client_library
from repository.errors import RecordNotFound
from repository.index import Index
from scheduler.client import ApiClient
from scheduler.errors import RemoteError

EXAMPLES = ("icreate-maze", "pr2-pick-place")  # controllers/examples/: each names its task
BRIDGE = BridgeConfig()
LAB = LabConfig()


def add_parser(commands: Any) -> None:
    demo = commands.add_parser("demo", help="serve the lab, submit the examples, show results")
    settings.add(demo, [settings.get("data")])
    demo.add_argument(
        "--http-port",
        type=int,
        help=f"HTTP port (default: {LAB.http_port} if free, else any free port)",
    )
    demo.add_argument(
        "--bridge-port",
        type=int,
        help=f"rosbridge port (default: {BRIDGE.port} if free, else any free port)",
    )
    demo.add_argument(
        "--sandbox",
        choices=["docker", "bwrap"],
        help="isolation backend (default: docker if an engine answers, else bwrap)",
    )
    demo.add_argument("--exit", action="store_true", help="stop the lab when the trials end")


def free_port(preferred: int, host: str = "127.0.0.1") -> int:
    """``preferred`` if nothing listens there, else a port the system picks."""
    for port in (preferred, 0):
        with socket.socket() as probe:
            try:
                probe.bind((host, port))
            except OSError:
                continue
            return int(probe.getsockname()[1])
    raise OSError("no free port")


def _serve_command(args: argparse.Namespace, http_port: int, bridge_port: int) -> list[str]:
    """The demo's ``labd serve``: this Python, the demo's folder and ports."""
    command = [sys.executable, "-m", "labd", "serve", "--data", str(args.data)]
    command += ["--http-port", str(http_port), "--bridge-port", str(bridge_port)]
    command += ["--allow-local-repos"]  # the examples are submitted by their repositories' paths
    if args.sandbox:
        command += ["--sandbox", args.sandbox]
    return command


def _already_served(data: Path) -> str | None:
    """Why the demo cannot start on ``data``: a lab serves it already (None: none does)."""
    running = datalock.holder(data)
    if running is None:
        return None
    where = running.get("http", "an address it has not written yet")
    return (
        f"labd demo: a lab already serves {data} at {where} (pid"
        f" {running.get('pid', '?')}): open that one, or stop it first"
    )


def main(args: argparse.Namespace) -> int:
    if refused := _already_served(args.data):  # before anything of its is rewritten
        print(refused, file=sys.stderr)
        return int(ExitCode.USAGE)
    # stopped with SIGTERM (a service manager, `kill`): stop the lab it started too
    signal.signal(signal.SIGTERM, _stop)
    args.data.mkdir(mode=0o700, parents=True, exist_ok=True)  # the lab's user's alone
    folder = (args.data / "demo").resolve()
    folder.mkdir(parents=True, exist_ok=True)
    repos = {name: make_repository(name, folder / name) for name in EXAMPLES}
    token = demo_token(args.data, folder)
    http_port = args.http_port if args.http_port is not None else free_port(LAB.http_port)
    bridge_port = args.bridge_port if args.bridge_port is not None else free_port(BRIDGE.port)
    server = f"http://127.0.0.1:{http_port}"
    env_file = folder / "env"
    env_file.write_text(f"export LABD_SERVER={server}\nexport LABD_TOKEN={token}\n")
    env_file.chmod(0o600)
    command = _serve_command(args, http_port, bridge_port)
    print("starting:", " ".join(command), flush=True)
    lab = subprocess.Popen(command)  # noqa: S603 - this Python, running labd serve
    client = ApiClient(server, token, connect_attempts=1)
    try:
        wait_for(client, lab)
        print(f"the lab: HTTP {server}, rosbridge ws://127.0.0.1:{bridge_port}", flush=True)
        submitted = []
        for name, repo in repos.items():
            row = client.post(
                "/api/trials",
                TrialDetail,
                json={"repository": str(repo), "ref": "main"},
            )
            print(f"submitted {name}: trial {row.id} at {row.commit[:12]}", flush=True)
            submitted.append(row.id)
        print("waiting for the trials (the first run builds the controller runtime)...")
        done = wait(client, submitted)
        print()
        for row in done:
            print(f"{headline(row)}  ({row.task})")
            print(f"  reward={row.reward}")
            if row.mcap:
                print(f"  record {row.mcap.url}")
        first = done[0]
        labd = Path(sys.executable).parent / "labd"
        print(
            f"""
Open the lab in a browser: {server}/
  {server}/trials/{first.id}               a trial: its outcome, plots, camera, logs, downloads
  {server}/robots/icreate-1          drive the maze robot; your drive is filed as a demonstration
  {server}/robots/pr2-1              move the PR2 from its 3D view
  {server}/docs                      the API, to try in a browser
  {server}/api/trials                the archive
  {server}/api/commits/{first.commit[:12]}   a commit, its trials and reruns
  ws://127.0.0.1:{bridge_port}/robots/icreate-1   a live robot, for roslibpy or roslibjs

Try (in another terminal; the env file carries the lab's address and your token):
  source {env_file}
  {labd} trials
  {labd} show {first.id}
  {labd} logs {first.id}
  {labd} download {first.id} -o trial.mcap
  {labd} rerun {first.commit[:12]} --wait
  {labd} export {first.id} --format lerobot
  {labd} submit {repos["icreate-maze"]} --ref main --seed 3 --wait
""",
            flush=True,
        )
        if args.exit:
            return int(worst(exit_code(r.status, r.outcome) for r in done))
        print("The lab keeps running; Ctrl-C stops it.", flush=True)
        return lab.wait()
    except RemoteError as err:
        print(f"labd demo: {err}", file=sys.stderr)
        return int(ExitCode.USAGE)
    except KeyboardInterrupt:
        return 0
    finally:
        client.close()
        if lab.poll() is None:
            lab.send_signal(signal.SIGINT)
            try:
                lab.wait(30)
            except subprocess.TimeoutExpired:
                lab.kill()


def _stop(signum: int, frame: object) -> None:
    raise SystemExit(128 + signum)


def make_repository(name: str, path: Path) -> Path:
    """The example ``name`` as a git repository at ``path``, committed on ``main``."""
    source = client_library() / "examples" / name
    if not (path / ".git").is_dir():
        path.mkdir(parents=True, exist_ok=True)
        _git(path, "init", "-q", "-b", "main")
    for item in source.iterdir():
        if item.name == "__pycache__":
            continue
        target = path / item.name
        if item.is_dir():
            shutil.copytree(item, target, dirs_exist_ok=True)
        else:
            shutil.copy2(item, target)
    _git(path, "add", "-A")
    if _git(path, "status", "--porcelain"):
        _git(path, "commit", "-q", "-m", f"the {name} example controller")
    return path


def demo_token(data: Path, folder: Path) -> str:
    """The demo user's token: the saved one if the archive still knows it, or a new one."""
    saved = folder / "token"
    data.mkdir(mode=0o700, parents=True, exist_ok=True)
    index = Index.open(ServiceConfig(data=data).database_url)
    try:
        if saved.exists() and index.user_by_token(saved.read_text().strip()):
            return saved.read_text().strip()
        name = "demo"
        while True:
            try:
                index.user(name)
            except RecordNotFound:
                break
            name = f"demo-{secrets.token_hex(2)}"
        token = index.add_user(name, max_running=2, max_daily=10_000)
    finally:
        index.close()
    saved.write_text(token + "\n")
    saved.chmod(0o600)
    return token


def wait_for(client: ApiClient, lab: subprocess.Popen[bytes]) -> None:
    deadline = time.monotonic() + 600  # the first start builds the controller runtime
    while time.monotonic() < deadline:
        if lab.poll() is not None:
            raise RemoteError(f"labd serve stopped (exit {lab.returncode}); its message is above")
        try:
            client.request("GET", "/api/tasks")
            return
        except RemoteError:
            time.sleep(0.5)
    raise RemoteError("labd serve did not answer within 10 minutes")


def _git(path: Path, *args: str) -> str:
    env = {
        **os.environ,
        "GIT_AUTHOR_NAME": "labd demo",
        "GIT_AUTHOR_EMAIL": "demo@localhost",
        "GIT_COMMITTER_NAME": "labd demo",
        "GIT_COMMITTER_EMAIL": "demo@localhost",
    }
    done = subprocess.run(  # noqa: S603 - git on the demo's own folders
        ["git", "-C", str(path), *args],  # noqa: S607
        check=True,
        capture_output=True,
        text=True,
        env=env,
    )
    return done.stdout.strip()
