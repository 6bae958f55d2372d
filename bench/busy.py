"""A busy lab beside the tests: ``labd serve`` running Docker trials the whole time.

    python bench/busy.py [--sandbox docker] [--workers 1] [--minutes 40]

starts ``labd serve`` on a data folder of its own (ports chosen by the system), and keeps
one trial of an example controller queued behind each worker until it is stopped (Ctrl-C,
SIGTERM) or ``--minutes`` pass; every minute it prints the trials it saw end. Run it,
then the suite (``make test`` or ``.ci/run`` from a fresh clone) beside it: the suite's
tests decide on behaviour, never on the machine's speed, so they pass beside it too
(issue 34's bar). It measures nothing itself.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import httpx

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "controllers" / "examples"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sandbox", default="docker", choices=["docker", "bwrap"])
    parser.add_argument("--workers", type=int, default=1)
    parser.add_argument("--minutes", type=float, default=40.0)
    parser.add_argument(
        "--example",
        default="dmc-cartpole-balance",
        help="the example controller its trials run (default: %(default)s, a 1,000-step"
        " episode; icreate-maze's are short, so its lab starts containers back to back)",
    )
    parser.add_argument(
        "--params",
        type=json.loads,
        default={},
        help="the task parameters of its trials, as JSON (e.g. '{\"maze_size\": 21}')",
    )
    args = parser.parse_args()
    work = Path(tempfile.mkdtemp(prefix="labd-busy-"))
    repo = work / "controller"
    shutil.copytree(EXAMPLES / args.example, repo)
    env = {**os.environ, "GIT_AUTHOR_NAME": "busy", "GIT_AUTHOR_EMAIL": "busy@example.org"}
    env |= {"GIT_COMMITTER_NAME": "busy", "GIT_COMMITTER_EMAIL": "busy@example.org"}
    for git in (["init", "-q", "-b", "main"], ["add", "-A"], ["commit", "-q", "-m", "example"]):
        subprocess.run(["git", *git], cwd=repo, env=env, check=True)
    data = work / "data"
    made = subprocess.run(
        [sys.executable, "-m", "labd", "users", "add", "busy", "--data", str(data), "--json",
         "--max-running", str(args.workers + 1), "--max-daily", "100000"],
        capture_output=True, text=True, check=True,
    )  # fmt: skip
    token = re.search(r'"token": "([^"]+)"', made.stdout)
    assert token is not None, made.stdout
    serve = subprocess.Popen(
        [sys.executable, "-m", "labd", "serve", "--data", str(data), "--cache", str(work / "c"),
         "--http-port", "0", "--bridge-port", "0", "--no-robots", "--workers",
         str(args.workers), "--sandbox", args.sandbox, "--allow-local-repos"],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True,
    )  # fmt: skip
    stop = False

    def stopping(_signal: int, _frame: object) -> None:
        nonlocal stop
        stop = True

    signal.signal(signal.SIGTERM, stopping)
    server = ""
    assert serve.stdout is not None
    for line in serve.stdout:
        if found := re.search(r"HTTP API on (https?://\S+?)/api", line):
            server = found.group(1)
        if line.startswith("  workers:"):
            break
    if not server:
        print("labd serve did not start", file=sys.stderr)
        return 1
    drain = threading.Thread(target=serve.stdout.read, daemon=True)  # its log, unread:
    drain.start()  # a full pipe would stop the lab at its next line
    print(f"busy lab on {server}: {args.workers} {args.sandbox} worker(s)", flush=True)
    client = httpx.Client(base_url=server, headers={"Authorization": f"Bearer {token[1]}"})
    pending: list[int] = []
    ended, seed, started = 0, 0, time.monotonic()
    outcomes: dict[str, int] = {}
    last = started
    try:
        while not stop and time.monotonic() - started < args.minutes * 60:
            while len(pending) < args.workers + 1:
                body = {"repository": str(repo), "seed": seed, "params": args.params}
                pending.append(client.post("/api/trials", json=body, timeout=60).json()["id"])
                seed += 1
            for trial in list(pending):
                row = client.get(f"/api/trials/{trial}", timeout=60).json()
                if row["status"] in ("finished", "cancelled"):
                    pending.remove(trial)
                    ended += 1
                    said = row["outcome"] or row["status"]
                    outcomes[said] = outcomes.get(said, 0) + 1
            if time.monotonic() - last >= 60:
                last = time.monotonic()
                minutes = (last - started) / 60
                print(f"{minutes:.0f} min: {ended} trials ended {outcomes}", flush=True)
            time.sleep(1)
    except KeyboardInterrupt:
        pass
    finally:
        serve.send_signal(signal.SIGTERM)
        try:
            serve.wait(60)
        except subprocess.TimeoutExpired:
            serve.kill()
        shutil.rmtree(work, ignore_errors=True)
    print(f"{ended} trials ended in {(time.monotonic() - started) / 60:.1f} min: {outcomes}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
