"""Make the golden records: real records filed by a real lab, for tests to hold later code to.

    python tests/data/records/make.py CHECKOUT [--out DIR]

runs ``labd serve`` from the labd checkout ``CHECKOUT`` (a ``git worktree`` of an older
commit, say) on a fresh data folder with one worker in bubblewrap and its robots, and
files there, as users do: a maze trial and a dm_control trial of the repository's
examples (each a git repository of its own), the first episode of an evaluation on the
maze's held-out suite (so run blind; the rest is cancelled), and a drive of the live maze
robot by a roslibpy client (a demonstration). It then stops the lab and copies each
record out as ``labd download`` gives it (``NAME.mcap`` and ``NAME.mcap.sig.json``, the
lab's signature), with the lab's public keys (``lab-keys.json``, as ``/api/keys``
answers) and ``index.json``: for each record, what it is, the digests the lab filed and
the commit of the code that made it. A record filed is never rewritten, so neither is a
file here: a new kind is a new file, made by the code of its day.
"""

from __future__ import annotations

import argparse
import json
import os
import queue
import re
import shutil
import signal
import sqlite3
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import httpx
import roslibpy

HERE = Path(__file__).resolve().parent
EXAMPLES = HERE.parents[2] / "controllers" / "examples"
GIT = {
    "GIT_AUTHOR_NAME": "golden",
    "GIT_AUTHOR_EMAIL": "golden@example.org",
    "GIT_COMMITTER_NAME": "golden",
    "GIT_COMMITTER_EMAIL": "golden@example.org",
    "GIT_AUTHOR_DATE": "2026-12-06T00:00:00Z",
    "GIT_COMMITTER_DATE": "2026-12-06T00:00:00Z",
}


class Lab:
    """``labd serve`` from the checkout, on ``data``."""

    def __init__(self, checkout: Path, work: Path) -> None:
        self.checkout = checkout
        self.data = work / "data"
        self.env = {**os.environ, "PYTHONPATH": str(checkout), "LABD_LOG_LEVEL": "WARNING"}
        self.env.pop("LABD_TOKEN", None)
        self.lines: queue.Queue[str] = queue.Queue()
        self.process = subprocess.Popen(
            [
                sys.executable, "-m", "labd", "serve", "--data", str(self.data),
                "--cache", str(work / "cache"), "--http-port", "0", "--bridge-port", "0",
                "--workers", "1", "--sandbox", "bwrap", "--allow-local-repos",
                "--videos", "asked",
            ],
            cwd=checkout, env=self.env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
            text=True, start_new_session=True,
        )  # fmt: skip
        threading.Thread(target=self._read, daemon=True).start()
        self.server = self.bridge = ""
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            line = self.lines.get(timeout=120)
            if not line:
                raise SystemExit("labd serve exited before it started")
            if found := re.search(r"rosbridge v2 on (wss?://\S+)", line):
                self.bridge = found.group(1).rstrip("/")
            if found := re.search(r"HTTP API on (https?://\S+?)/api", line):
                self.server = found.group(1)
            if line.startswith("  workers:"):
                break
        self.token = json.loads(self.labd("users", "add", "golden", "--data", str(self.data),
                                          "--json"))["token"]  # fmt: skip

    def _read(self) -> None:
        assert self.process.stdout is not None
        for line in self.process.stdout:
            sys.stderr.write("  lab: " + line)
            self.lines.put(line)
        self.lines.put("")

    def labd(self, *args: str) -> str:
        env = {**self.env, "LABD_SERVER": self.server, "LABD_TOKEN": getattr(self, "token", "")}
        done = subprocess.run(
            [sys.executable, "-m", "labd", *args],
            cwd=self.checkout, env=env, capture_output=True, text=True, check=False,
        )  # fmt: skip
        if done.returncode not in (0, 1):
            raise SystemExit(f"labd {' '.join(args)}: {done.returncode}\n{done.stderr}")
        return done.stdout

    def post(self, path: str, body: dict[str, Any]) -> dict[str, Any]:
        answer = httpx.post(
            self.server + path,
            json=body,
            headers={"Authorization": f"Bearer {self.token}"},
            timeout=60,
        )
        answer.raise_for_status()
        found: dict[str, Any] = answer.json()
        return found

    def get(self, path: str) -> dict[str, Any]:
        answer = httpx.get(
            self.server + path, headers={"Authorization": f"Bearer {self.token}"}, timeout=60
        )
        answer.raise_for_status()
        found: dict[str, Any] = answer.json()
        return found

    def stop(self) -> None:
        self.process.send_signal(signal.SIGTERM)
        self.process.wait(120)


def repository(work: Path, example: str) -> Path:
    """The example as a git repository of its own (a fixed author and date)."""
    path = work / "repos" / example
    shutil.copytree(EXAMPLES / example, path)
    env = {**os.environ, **GIT}
    for args in (["init", "-q", "-b", "main"], ["add", "-A"], ["commit", "-q", "-m", example]):
        subprocess.run(["git", *args], cwd=path, env=env, check=True)
    return path


def drive(lab: Lab) -> None:
    """Take the maze robot with /lab/drive, drive it forward, leave: a demonstration."""
    ros = roslibpy.Ros(host=lab.bridge + "/robots/icreate-1")
    ros.run(timeout=30)
    try:
        answer = roslibpy.Service(ros, "/lab/drive", "lab_msgs/srv/Drive").call(
            roslibpy.ServiceRequest({"session": "golden-1", "interface": "script", "user": ""}),
            timeout=30,
        )
        assert answer["success"], answer
        cmd = roslibpy.Topic(ros, "/cmd_vel", "geometry_msgs/msg/Twist")
        odom: list[Any] = []
        roslibpy.Topic(ros, "/odom", "nav_msgs/msg/Odometry").subscribe(odom.append)
        deadline = time.monotonic() + 60
        while len(odom) < 40 and time.monotonic() < deadline:
            cmd.publish(roslibpy.Message({"linear": {"x": 0.2}, "angular": {"z": 0.3}}))
            time.sleep(0.05)
        assert len(odom) >= 40, "the robot did not answer"
    finally:
        ros.close()


def wait(what: str, ready: Any, timeout: float = 600) -> Any:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if found := ready():
            return found
        time.sleep(0.5)
    raise SystemExit(f"waited {timeout:.0f} s for {what}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkout", type=Path, help="the labd checkout that makes them")
    parser.add_argument("--out", type=Path, default=HERE)
    args = parser.parse_args()
    checkout = args.checkout.resolve()
    commit = subprocess.run(
        ["git", "rev-parse", "HEAD"], cwd=checkout, capture_output=True, text=True, check=True
    ).stdout.strip()
    work = Path(tempfile.mkdtemp(prefix="labd-golden-"))
    lab = Lab(checkout, work)
    made: dict[str, tuple[str, str]] = {}  # name -> (how it was asked for, what it is)
    try:
        maze = lab.post("/api/trials", {
            "repository": str(repository(work, "icreate-maze")), "task": "icreate-maze",
            "seed": 11, "params": {"time_limit": 20.0},
        })  # fmt: skip
        dmc = lab.post("/api/trials", {
            "repository": str(repository(work, "dmc-cartpole-balance")),
            "task": "dmc-cartpole-balance", "seed": 5,
        })  # fmt: skip
        ids = {"trial-maze": maze["id"], "trial-dmc": dmc["id"]}
        for name, trial_id in ids.items():
            wait(name, lambda t=trial_id: lab.get(f"/api/trials/{t}")["status"] == "finished")
        held = lab.post("/api/evaluations", {
            "repository": str(work / "repos" / "icreate-maze"), "task": "icreate-maze",
            "suite": "test",
        })  # fmt: skip

        db = lab.data / "index.sqlite"

        def first_filed() -> int | None:
            with sqlite3.connect(db) as con:
                row = con.execute(
                    "select trial_id from evaluation_episodes join trials"
                    " on trials.id = evaluation_episodes.trial_id where evaluation_id = ?"
                    " and trials.status = 'finished' and trials.signature is not null"
                    " order by trial_id limit 1",
                    (held["id"],),
                ).fetchone()
            return int(row[0]) if row else None

        ids["trial-held-out-blind"] = wait("a held-out episode filed", first_filed)
        lab.post(f"/api/evaluations/{held['id']}/cancel", {})
        drive(lab)

        def demonstration() -> int | None:
            with sqlite3.connect(db) as con:
                row = con.execute(
                    "select id from trials where kind = 'demonstration' and signature is not null"
                ).fetchone()
            return int(row[0]) if row else None

        ids["drive-maze"] = wait("the drive filed", demonstration)
        keys = httpx.get(lab.server + "/api/keys", timeout=30).json()
    finally:
        lab.stop()
    made = {
        "trial-maze": ("POST /api/trials, the icreate-maze example, seed 11, 20 s", "trial"),
        "trial-dmc": ("POST /api/trials, the dmc-cartpole-balance example, seed 5", "trial"),
        "trial-held-out-blind": (
            "POST /api/evaluations on icreate-maze's held-out suite: its first episode",
            "trial, run blind",
        ),
        "drive-maze": ("a roslibpy client drove icreate-1 with /lab/drive", "demonstration"),
    }
    args.out.mkdir(parents=True, exist_ok=True)
    index: dict[str, Any] = {}
    with sqlite3.connect(lab.data / "index.sqlite") as con:
        for name, trial_id in ids.items():
            mcap, signature, manifest_digest, data_digest = con.execute(
                "select mcap, signature, manifest_digest, data_digest from trials where id = ?",
                (trial_id,),
            ).fetchone()
            hex_ = mcap.removeprefix("sha256:")
            shutil.copyfile(
                lab.data / "blobs" / "sha256" / hex_[:2] / hex_, args.out / f"{name}.mcap"
            )
            signed = json.loads(signature) if isinstance(signature, str) else signature
            (args.out / f"{name}.mcap.sig.json").write_text(
                json.dumps(signed, indent=2, sort_keys=True) + "\n"
            )
            asked, what = made[name]
            index[name] = {
                "what": what,
                "asked": asked,
                "manifest_digest": manifest_digest,
                "data_digest": data_digest,
                "labd": commit,
            }
    (args.out / "lab-keys.json").write_text(json.dumps(keys, indent=2, sort_keys=True) + "\n")
    (args.out / "index.json").write_text(json.dumps(index, indent=2, sort_keys=True) + "\n")
    shutil.rmtree(work, ignore_errors=True)
    print(f"{len(index)} records in {args.out}")


if __name__ == "__main__":
    main()
