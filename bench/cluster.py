"""What a Ray cluster costs an evaluation: the same episodes through a cluster's nodes and
through the lab's own workers, on the same machine.

A short maze controller (as ``tests/integration/test_evaluate.py``'s: five ticks forward,
never solved), evaluated on the maze's ``dev`` suite (20 episodes), queued with ``labd
evaluate`` as a user does and followed through the API, by:

- **local** (the baseline): ``labd serve --workers 2``, two bubblewrap workers in the
  lab's process, each replaying what it files beside its next trial;
- **cluster**: ``labd serve --workers 0 --ray-address ADDRESS`` on a loopback Ray cluster
  made here (``ray.cluster_utils.Cluster``, bound to 127.0.0.1: a head with no CPU, two
  nodes of one ``labd_sim`` slot each), whose nodes run the trials and replay each
  other's records, a replay holding a slot as a trial does.

Both have two slots. The cluster is up during the baseline too, so its idle daemons weigh
on both. Videos are rendered only when asked (``--videos asked``), for less noise. Each
lab first runs the evaluation once unmeasured, as a lab that has been up a while: its
processes started and their imports made (on the cluster, each node's Ray worker and
helper; locally, the lab's helpers), then the measured one (``--cold``: no warm-up).

It prints each run's episodes per hour (from queueing to the last episode filed, and to
its last replay's verdict) and the ratio, cluster to local. Then the dispatch overhead per
episode, as medians over the episodes, from the index's times (``started``: the claim;
``finished``: filed; ``wall_seconds``: the trial's own run, checkout to the record
written) and the controller's own clock (it prints the time of its first step, read
back from its stdout log; bubblewrap shares the host's clock):

- claim to the first step (checkout, sandbox, controller start; on the cluster also the
  Ray task's scheduling and the node's worker set-up);
- claim to filed, minus the trial's own run (on the cluster: the task's scheduling, its
  wait for a slot a replay holds, the record's way back and the filing; locally: the
  filing);
- a slot's time per episode (seconds to the last filed times slots, over episodes) minus
  the trial's own run: what each episode costs a slot beyond running, idle gaps between
  claims included;
- a slot freed (an episode filed) to the next claim, while every slot was busy;
- on the cluster, a task sent to its start on the node (the lab's log: ``began on NODE
  S s after it was sent``).

Each as the cluster's extra over local, and as a share of an episode's time (the local
claim to filed). The dispatch overhead is what the cluster adds to an episode beyond
what a worker does: the task's way to its node (sent to its start) and back (claim to
filed beyond the trial's own run, the cluster's extra); the issue's target is at most
5 % of an episode's time.

    .venv/bin/python bench/cluster.py [--suite dev] [--rounds 3] [--json]
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import queue
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import httpx

ROOT = Path(__file__).resolve().parent.parent
TARGET = 0.05  # the dispatch overhead, of an episode's time (issue 35)
SLOTS = 2
LAB_TOML = '[controller]\ncommand = ["python", "c.py"]\ntask = "icreate-maze"\n'
CONTROLLER = '''\
"""Drives forward for five ticks, then stops (the maze is never solved); prints the
host's time as it makes its first step, for bench/cluster.py."""
import time

from controllers.client import Lab

with Lab.connect() as lab:
    for tick in range(5):
        lab.publish("/cmd_vel", "geometry_msgs/msg/Twist", {"linear": {"x": 0.2}})
        if tick == 0:
            print("first step", time.time(), flush=True)
        lab.step()
'''


def repository(folder: Path) -> Path:
    """The controller as a git repository of its own."""
    folder.mkdir(parents=True)
    (folder / "lab.toml").write_text(LAB_TOML)
    (folder / "c.py").write_text(CONTROLLER)
    git = ["git", "-C", str(folder), "-c", "user.name=bench", "-c", "user.email=bench@example.org"]
    subprocess.run([*git, "init", "-q", "-b", "main"], check=True)
    subprocess.run([*git, "add", "-A"], check=True)
    subprocess.run([*git, "commit", "-qm", "five ticks"], check=True)
    return folder


@contextmanager
def loopback_cluster() -> Iterator[str]:
    """A Ray cluster on 127.0.0.1 (a head with no CPU, two nodes of one slot); its
    address (its ports are ones the system picks: another cluster here is no clash)."""
    os.environ["RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"] = "0"  # here and in the labs started
    # Ray runs its workers at niceness 15, below its daemons and the lab; on a node of its
    # own that changes nothing, but here the nodes share two cores with the lab: as its
    # own workers do, they run at the lab's
    os.environ.setdefault("RAY_worker_niceness", "0")
    from ray.cluster_utils import Cluster  # noqa: PLC0415 (labd[cluster]'s, only here)

    head = {"num_cpus": 0, "include_dashboard": False}
    made = Cluster(initialize_head=True, head_node_args=head)
    try:
        for _ in range(SLOTS):
            made.add_node(num_cpus=1, resources={"labd_sim": 1})
        made.wait_for_nodes()
        yield made.address
    finally:
        made.shutdown()


class Served:
    """A `labd serve` process on a data folder of its own; its output drained by a
    thread (a full pipe would stop it) and kept."""

    def __init__(self, data: Path, cache: Path, *extra: str) -> None:
        self.data = data
        made = subprocess.run(
            [sys.executable, "-m", "labd", "users", "add", "bench", "--data", str(data),
             "--max-running", str(SLOTS), "--json"],
            capture_output=True, text=True, check=True,
        )  # fmt: skip
        self.token = json.loads(made.stdout)["token"]
        self.process = subprocess.Popen(
            [sys.executable, "-m", "labd", "serve", "--data", str(data), "--cache", str(cache),
             "--http-port", "0", "--bridge-port", "0", "--no-robots", "--sandbox", "bwrap",
             "--allow-local-repos", "--videos", "asked", *extra],
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
            start_new_session=True,
        )  # fmt: skip
        self.output: list[str] = []
        lines: queue.Queue[str] = queue.Queue()

        def drain() -> None:
            assert self.process.stdout is not None
            for line in self.process.stdout:
                self.output.append(line)
                lines.put(line)
            lines.put("")

        self.reader = threading.Thread(target=drain, daemon=True)
        self.reader.start()
        deadline = time.monotonic() + 300
        while time.monotonic() < deadline:
            line = lines.get(timeout=max(0.1, deadline - time.monotonic()))
            if not line:
                raise RuntimeError("labd serve exited:\n" + "".join(self.output[-40:]))
            if found := re.search(r"HTTP API on (http://\S+?)/api", line):
                self.server = found.group(1)
                return
        self.stop()
        raise RuntimeError("labd serve did not start:\n" + "".join(self.output[-40:]))

    def labd(self, *args: str) -> Any:
        env = {**os.environ, "LABD_SERVER": self.server, "LABD_TOKEN": self.token}
        done = subprocess.run(
            [sys.executable, "-m", "labd", *args, "--json"],
            capture_output=True, text=True, env=env, timeout=300, check=True,
        )  # fmt: skip
        return json.loads(done.stdout)

    def stop(self) -> None:
        if self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(60)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait(10)
        self.reader.join(30)


def seconds(stamp: str) -> float:
    return dt.datetime.fromisoformat(stamp).timestamp()


def evaluate(served: Served, repo: Path, suite: str) -> dict[str, Any]:
    """Queue an evaluation with ``labd evaluate``, follow it to its last replay's verdict;
    its figures, per episode and in all."""
    headers = {"Authorization": f"Bearer {served.token}"}
    with httpx.Client(base_url=served.server, headers=headers, timeout=120) as client:
        evaluation = served.labd("evaluate", str(repo), "--suite", suite)
        path = f"/api/evaluations/{evaluation['id']}"
        deadline = time.monotonic() + 900
        while not (
            evaluation["status"] in ("finished", "cancelled")
            and all(r["verified"] is not None for r in evaluation["rows"])
        ):
            if time.monotonic() > deadline:
                raise RuntimeError("the evaluation did not end:\n" + "".join(served.output[-40:]))
            time.sleep(0.25)
            evaluation = client.get(path).json()
            print(f"[bench]   {evaluation['done']}/{evaluation['episodes']}", end="\r",
                  file=sys.stderr)  # fmt: skip
        verified = time.time()
        print(file=sys.stderr)
        episodes = [episode(client, row) for row in evaluation["rows"]]
    ours = {row["trial"] for row in evaluation["rows"]}
    said = re.findall(r"trial (\d+): began on \S+ (-?[\d.]+) s after it was sent",
                      "".join(served.output))  # fmt: skip
    began = [float(seconds) for trial, seconds in said if int(trial) in ours]
    # from queueing (the index's time: not the command's start) to the last episode filed
    # (the index's time, no poll in it) and to the last verdict (seen by the poll)
    queued = min(e["created"] for e in episodes)
    to_filed = max(e["finished"] for e in episodes) - queued
    to_verified = verified - queued
    n = len(episodes)
    run = {
        "episodes": n,
        "outcomes": sorted({e["outcome"] for e in episodes}),
        "verified": sum(e["verified"] is True for e in episodes),
        "workers": sorted({e["worker"] for e in episodes}),
        "seconds_to_filed": round(to_filed, 2),
        "seconds_to_verified": round(to_verified, 2),
        "per_hour_filed": 3600 * n / to_filed,
        "per_hour_verified": 3600 * n / to_verified,
        "claim_wait": claim_wait(episodes),
        "sent_to_began": statistics.median(began) if began else 0.0,
    }
    for name in ("claim_to_first_step", "claim_to_filed", "own_run", "beyond_run"):
        values = [e[name] for e in episodes if e[name] is not None]
        run[name] = statistics.median(values) if values else None
        run[name + "_mean"] = statistics.fmean(values) if values else None
    # what an episode costs a slot beyond its own run, idle gaps between claims included
    run["slot_per_episode"] = to_filed * SLOTS / n
    run["slot_beyond_run"] = run["slot_per_episode"] - run["own_run_mean"]
    return run


def episode(client: httpx.Client, row: dict[str, Any]) -> dict[str, Any]:
    """One episode's times: the index's, and its controller's first step (its stdout)."""
    trial = client.get(f"/api/trials/{row['trial']}").json()
    stdout = client.get(trial["logs"]["stdout"]).text if trial["logs"].get("stdout") else ""
    first = re.search(r"^first step (\S+)$", stdout, re.MULTILINE)
    started, finished = seconds(trial["started"]), seconds(trial["finished"])
    return {
        "worker": trial["worker"],
        "outcome": trial["outcome"],
        "verified": row["verified"],
        "created": seconds(trial["created"]),
        "started": started,
        "finished": finished,
        "claim_to_first_step": float(first.group(1)) - started if first else None,
        "claim_to_filed": finished - started,
        "own_run": trial["wall_seconds"],
        "beyond_run": finished - started - trial["wall_seconds"],
    }


def claim_wait(episodes: list[dict[str, Any]]) -> float:
    """Median seconds from a slot freed (an episode filed) to the next claim, over the
    claims made while every slot was busy (all but the first ``SLOTS``)."""
    filed = sorted(e["finished"] for e in episodes)
    waits = []
    for e in sorted(episodes, key=lambda e: e["started"])[SLOTS:]:
        before = [f for f in filed if f <= e["started"]]
        if before:
            waits.append(e["started"] - before[-1])
    return statistics.median(waits) if waits else 0.0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--suite", default="dev", help="the maze's suite (default: dev, 20)")
    parser.add_argument(
        "--rounds", type=int, default=3, help="local then cluster, N times (default: 3)"
    )
    parser.add_argument("--cache", type=Path, default=ROOT / "lab-data" / "cache")
    parser.add_argument(
        "--cold", action="store_true", help="measure each lab's first evaluation (no warm-up)"
    )
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    args.cache.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix="bench-cluster-"))
    work.chmod(0o755)
    repo = repository(work / "five-ticks")
    runs: dict[str, list[dict[str, Any]]] = {"local": [], "cluster": []}
    try:
        print("[bench] the loopback cluster", file=sys.stderr)
        with loopback_cluster() as address:
            ways = {
                "local": ("--workers", str(SLOTS)),
                "cluster": ("--workers", "0", "--ray-address", address),
            }
            for round_ in range(args.rounds):
                for way, extra in ways.items():
                    print(f"[bench] {way}, round {round_ + 1}", file=sys.stderr)
                    served = Served(work / f"data-{way}-{round_}", args.cache, *extra)
                    try:
                        if not args.cold:
                            evaluate(served, repo, args.suite)  # its processes warmed
                        runs[way].append(evaluate(served, repo, args.suite))
                    finally:
                        served.stop()
    finally:
        shutil.rmtree(work, ignore_errors=True)
    results = {"suite": args.suite, "slots": SLOTS, "cpus": os.cpu_count(), "runs": runs}
    results["summary"] = summary(runs)
    if args.json:
        print(json.dumps(results, indent=2))
        return
    report(results)


def summary(runs: dict[str, list[dict[str, Any]]]) -> dict[str, Any]:
    """Each figure's median over the rounds, per way; the ratios, cluster to local; the
    cluster's extra per episode, as a share of an episode's time (local claim to filed)."""

    def median(way: str, name: str) -> float:
        return statistics.median(r[name] for r in runs[way])

    names = ("per_hour_filed", "per_hour_verified", "claim_to_first_step", "claim_to_filed",
             "own_run", "beyond_run", "beyond_run_mean", "slot_beyond_run",
             "claim_wait", "sent_to_began")  # fmt: skip
    out: dict[str, Any] = {way: {n: median(way, n) for n in names} for way in runs}
    local, cluster = out["local"], out["cluster"]
    out["ratio_filed"] = cluster["per_hour_filed"] / local["per_hour_filed"]
    out["ratio_verified"] = cluster["per_hour_verified"] / local["per_hour_verified"]
    episode_time = local["claim_to_filed"]
    out["episode_seconds"] = episode_time
    out["extra"] = {
        name: {
            "seconds": cluster[name] - local[name],
            "of_episode": (cluster[name] - local[name]) / episode_time,
        }
        for name in ("claim_to_first_step", "beyond_run", "slot_beyond_run", "claim_wait")
    }
    # the dispatch overhead: the task's way to its node and back
    dispatch = cluster["sent_to_began"] + max(0.0, out["extra"]["beyond_run"]["seconds"])
    out["dispatch"] = {"seconds": dispatch, "of_episode": dispatch / episode_time}
    # the shortest episode (claim to filed, locally) for which it is within target
    out["target_met_from_seconds"] = dispatch / TARGET
    return out


def report(results: dict[str, Any]) -> None:
    s = results["summary"]
    n = results["runs"]["local"][0]["episodes"]
    rounds = len(results["runs"]["local"])
    print(f"A {n}-episode maze evaluation (suite {results['suite']}) of a five-tick controller,")
    print(f"  labd serve with bubblewrap, {results['slots']} slots each way; {results['cpus']}"
          f" CPUs; medians over {rounds} round(s)\n")  # fmt: skip
    print(f"  {'episodes per hour':24} {'to filed':>9} {'to verified':>12}")
    for way, label in (("local", "local (--workers 2)"), ("cluster", "cluster (2 nodes x 1)")):
        print(f"  {label:24} {s[way]['per_hour_filed']:9.0f} {s[way]['per_hour_verified']:12.0f}")
    print(f"  {'cluster / local':24} {s['ratio_filed']:9.2f} {s['ratio_verified']:12.2f}")
    for way, runs in results["runs"].items():  # the spread: this machine is noisy
        each = ", ".join(f"{r['per_hour_filed']:.0f}" for r in runs)
        print(f"  {way} each round, to filed: {each}")
    print()
    print(f"  {'per episode (medians), s':44} {'local':>7} {'cluster':>8} {'extra':>7}"
          f" {'of an episode':>14}")  # fmt: skip
    rows = (
        ("claim to the first step", "claim_to_first_step"),
        ("claim to filed, beyond the trial's own run", "beyond_run"),
        ("a slot's time, beyond the trial's own run", "slot_beyond_run"),
        ("a slot freed to the next claim", "claim_wait"),
    )
    for label, name in rows:
        extra = s["extra"][name]
        print(f"  {label:44} {s['local'][name]:7.2f} {s['cluster'][name]:8.2f}"
              f" {extra['seconds']:7.2f} {extra['of_episode']:13.1%}")  # fmt: skip
    own = "the trial's own run (checkout to record)"
    print(f"  {own:44} {s['local']['own_run']:7.2f}"
          f" {s['cluster']['own_run']:8.2f}")  # fmt: skip
    sent = "a task sent to its start on the node"
    print(f"  {sent:44} {'':7} {s['cluster']['sent_to_began']:8.3f}")
    print(f"  {'an episode (local claim to filed)':44} {s['episode_seconds']:7.2f}\n")
    extra = s["dispatch"]["of_episode"]
    verdict = "PASS" if extra <= TARGET else "FAIL"
    print(f"  {verdict}  the cluster's dispatch overhead per episode (to the node and back)"
          f" <= {TARGET:.0%} of an episode's time ({s['dispatch']['seconds']:.3f} s,"
          f" {extra:.1%}; met by episodes of"
          f" {s['target_met_from_seconds']:.1f} s or more)")  # fmt: skip


if __name__ == "__main__":
    main()
