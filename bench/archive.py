"""The archive and the queue: query speed at scale, submit-to-running, throughput.

1. **Index queries over 100,000 synthetic records** (SQLite, and PostgreSQL when
   ``LABD_TEST_POSTGRES_URL`` is set): the commit page and filtered lists (by status
   and task, by user, by repository, by commit prefix, the second page of a list).
   p50 and p95 of each, against a primary-key lookup measured in the same run.
   Target: p95 under 50 ms for the commit page and for filtered lists.
2. **Submit to running** with a warm mirror: ``labd serve``'s API and one worker in
   this process, a local git repository; from the POST to the worker's claim (the
   trial's ``started``). Baseline: resolving the ref alone (the fetch the submission
   makes). Target: under 2 s.
3. **Trials per minute** on a short task (the maze with a 2 s time limit, a controller
   that drives until the episode ends), with 1 and then 2 workers; the ratio is the
   speed-up of the second worker on this 2-core machine.

    .venv/bin/python bench/archive.py [--records 100000] [--trials 6] [--json]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import random
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import httpx
import sqlalchemy as sa

from labd.api.app import create_app
from labd.api.server import HttpServer
from labd.service import Service, ServiceConfig
from repository.index import Filters, Index, connect
from repository.trial import Outcome, Status
from scheduler.fetch import FetchPolicy, resolve

ROOT = Path(__file__).resolve().parent.parent
TASKS = ("icreate-maze", "pr2-table")
LOCAL = FetchPolicy(schemes=frozenset({"file"}))  # the benchmark submits a local repository
# (status, outcome): mostly finished, some of each outcome, a few cancelled or waiting
ENDINGS = (
    [("finished", "success")] * 4
    + [("finished", "fail")] * 2
    + [("finished", "error")] * 2
    + [("cancelled", None), ("queued", None)]
)
CONTROLLER = """\
from controllers.client import Lab, EpisodeOver
with Lab.connect() as lab:
    while True:
        lab.publish("/cmd_vel", "geometry_msgs/msg/Twist", {"linear": {"x": 0.2}})
        try:
            lab.step()
        except EpisodeOver:
            break
"""


# -- 1. index queries ---------------------------------------------------------------------


def synthetic(n: int, rng: random.Random) -> list[dict[str, Any]]:
    repos = [
        f"https://git.example.org/group{g}/controller{r}.git" for g in range(50) for r in range(20)
    ]
    commits = [f"{rng.getrandbits(160):040x}" for _ in range(n // 10)]
    users = [f"user{u}" for u in range(200)]
    start = 1.7e9
    rows = []
    for i in range(n):
        c = rng.randrange(len(commits))
        status, outcome = rng.choice(ENDINGS)
        rows.append(
            {
                "repository": repos[c % len(repos)],
                "ref": "main",
                "commit": commits[c],
                "task": TASKS[c % 2],
                "params": {"maze_size": 9},
                "seed": rng.randrange(100),
                "submitter": users[c % len(users)],
                "public": rng.random() < 0.8,
                "rerun_of": (i - rng.randrange(1, 50)) if i > 50 and rng.random() < 0.1 else None,
                "kind": "trial",
                "status": status,
                "outcome": outcome,
                "reason": "the task was achieved at tick 900: reached the goal",
                "created": start + i * 30.0,
                "started": start + i * 30.0 + 1,
                "finished": start + i * 30.0 + 20,
                "attempts": 1,
                "cancel_requested": False,
                "manifest": {"schema": "labd.trial/1", "seed": i},
                "manifest_digest": f"{rng.getrandbits(256):064x}",
                "data_digest": f"{rng.getrandbits(256):064x}",
                "metrics": {"success": True, "reward": 1.0},
                "mcap": f"sha256:{rng.getrandbits(256):064x}",
                "mcap_size": 1_000_000,
                "reproduced": True if i % 10 == 0 else None,
            }
        )
    return rows


def timed(fn: Callable[[], Any], repeat: int) -> list[float]:
    fn()  # warm
    out = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        out.append((time.perf_counter() - t) * 1000)
    return out


def pct(values: list[float], q: float) -> float:
    return statistics.quantiles(values, n=100)[int(q) - 1]


def bench_index(url: str, n: int, repeat: int, rng: random.Random) -> dict[str, Any]:
    index = Index(connect(url))
    index.create()
    rows = synthetic(n, rng)
    t = time.perf_counter()
    for start in range(0, n, 5000):
        index.bulk_insert(rows[start : start + 5000])
    load = time.perf_counter() - t
    commits = [r["commit"] for r in rows]
    users = sorted({r["submitter"] for r in rows})
    repos = sorted({r["repository"] for r in rows})
    page2 = index.find(Filters(outcome=Outcome.SUCCESS), limit=50).next
    queries: dict[str, Callable[[], Any]] = {
        "baseline: one trial by id": lambda: index.trial(rng.randrange(1, n)),
        "commit page": lambda: index.commit_page(rng.choice(commits)),
        "commit page by 8-digit prefix": lambda: index.commit_page(rng.choice(commits)[:8]),
        "list: outcome + task": lambda: index.find(
            Filters(outcome=Outcome.ERROR, task=rng.choice(TASKS))
        ),
        "list: user": lambda: index.find(Filters(submitter=rng.choice(users))),
        "list: repository": lambda: index.find(Filters(repository=rng.choice(repos))),
        "list: user + time range": lambda: index.find(
            Filters(submitter=rng.choice(users), since=1.7e9 + n * 10, until=1.7e9 + n * 20)
        ),
        "list: second page": lambda: index.find(
            Filters(outcome=Outcome.SUCCESS), limit=50, before=page2
        ),
        "list: queued (the queue's view)": lambda: index.find(Filters(status=Status.QUEUED)),
    }
    results = {}
    for name, fn in queries.items():
        times = timed(fn, repeat)
        results[name] = {"p50_ms": statistics.median(times), "p95_ms": pct(times, 95)}
    base = results["baseline: one trial by id"]["p95_ms"]
    for value in results.values():
        value["p95_ratio"] = value["p95_ms"] / base
    index.close()
    return {"records": n, "load_seconds": load, "queries": results}


# -- 2 and 3. the service ------------------------------------------------------------------


def make_repo(path: Path) -> Path:
    path.mkdir(parents=True)
    (path / "lab.toml").write_text('[controller]\ncommand = ["python", "c.py"]\n')
    (path / "c.py").write_text(CONTROLLER)
    env = {
        **os.environ,
        "GIT_AUTHOR_NAME": "b",
        "GIT_AUTHOR_EMAIL": "b@x",
        "GIT_COMMITTER_NAME": "b",
        "GIT_COMMITTER_EMAIL": "b@x",
    }
    for args in (["init", "-q", "-b", "main"], ["add", "-A"], ["commit", "-q", "-m", "c"]):
        subprocess.run(["git", "-C", str(path), *args], check=True, env=env)
    return path


async def bench_service(folder: Path, trials: int, sandbox: str | None) -> dict[str, Any]:
    repo = make_repo(folder / "repo")
    cache = ROOT / ".pytest_cache" / "d" / "labd-trials"  # the tests' runtime, if built
    out: dict[str, Any] = {}
    for workers in (1, 2):
        config = ServiceConfig(
            data=folder / f"data-{workers}",
            cache=cache if cache.is_dir() else None,
            workers=workers,
            sandbox=sandbox,
            heartbeat=5.0,
            fetch=LOCAL,
        )
        service = Service(config)
        http = HttpServer(create_app(service), "127.0.0.1", 0)
        await http.start()
        await service.start()
        token = service.index.add_user("bench", max_running=workers, max_daily=10_000)
        async with httpx.AsyncClient(
            base_url=http.url(), headers={"Authorization": f"Bearer {token}"}, timeout=120
        ) as client:
            body = {"repository": str(repo), "ref": "main", "task": "icreate-maze"}
            body["params"] = {"time_limit": 2.0}
            await client.post("/api/trials", json=body)  # warms the mirror
            latencies, resolves = [], []
            if workers == 1:
                for _ in range(5):
                    await wait_idle(service)
                    t = time.perf_counter()
                    await asyncio.to_thread(resolve, str(repo), "main", service.cache, LOCAL)
                    resolves.append(time.perf_counter() - t)
                    posted = time.time()
                    reply = (await client.post("/api/trials", json=body)).json()
                    started = await wait_started(service, reply["id"])
                    latencies.append(started - posted)
                out["submit_to_running_s"] = statistics.median(latencies)
                out["resolve_s"] = statistics.median(resolves)
            await wait_idle(service)
            t = time.perf_counter()
            ids = []
            for seed in range(trials):
                reply = await client.post("/api/trials", json={**body, "seed": seed})
                ids.append(reply.json()["id"])
            await wait_idle(service)
            elapsed = time.perf_counter() - t
            rows = [service.index.trial(i) for i in ids]
            # 2 s of maze: each runs to its end short of the goal, a fail; an error is a bug
            bad = [r for r in rows if r.outcome is not Outcome.FAIL]
            if bad:
                raise SystemExit(f"trials broke: {[(r.id, r.reason) for r in bad]}")
            out[f"trials_per_minute_{workers}_workers"] = trials / elapsed * 60
        await http.close()
        await service.close()
    out["speedup_2_workers"] = (
        out["trials_per_minute_2_workers"] / out["trials_per_minute_1_workers"]
    )
    return out


async def wait_started(service: Service, trial_id: int) -> float:
    while True:
        row = service.index.trial(trial_id)
        if row.started is not None:
            return row.started.timestamp()
        await asyncio.sleep(0.01)


async def wait_idle(service: Service) -> None:
    while True:
        page = service.index.find(Filters(status=Status.QUEUED), limit=1).items
        page += service.index.find(Filters(status=Status.RUNNING), limit=1).items
        if not page:
            return
        await asyncio.sleep(0.05)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--records", type=int, default=100_000)
    parser.add_argument("--repeat", type=int, default=200)
    parser.add_argument("--trials", type=int, default=6)
    parser.add_argument("--sandbox", choices=["docker", "bwrap"], default="bwrap")
    parser.add_argument("--skip-service", action="store_true")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    rng = random.Random(7)
    report: dict[str, Any] = {}
    with tempfile.TemporaryDirectory(prefix="labd-bench-") as tmp:
        folder = Path(tmp)
        report["sqlite"] = bench_index(
            f"sqlite:///{folder / 'bench.sqlite'}", args.records, args.repeat, rng
        )
        pg = os.environ.get("LABD_TEST_POSTGRES_URL")
        if pg:
            report["postgresql"] = bench_postgres(pg, args.records, args.repeat, rng)
        if not args.skip_service:
            report["service"] = asyncio.run(bench_service(folder, args.trials, args.sandbox))
    if args.json:
        print(json.dumps(report, indent=2))
        return
    for db in ("sqlite", "postgresql"):
        if db not in report:
            continue
        r = report[db]
        print(f"index on {db}: {r['records']:,} records (loaded in {r['load_seconds']:.1f} s)")
        for name, q in r["queries"].items():
            mark = (
                ""
                if name.startswith("baseline")
                else ("  ok" if q["p95_ms"] < 50 else "  OVER 50 ms")
            )
            print(
                f"  {name:<34} p50 {q['p50_ms']:7.2f} ms  p95 {q['p95_ms']:7.2f} ms"
                f"  ({q['p95_ratio']:5.1f}x baseline){mark}"
            )
    if "service" in report:
        s = report["service"]
        print("service (one process, bubblewrap workers):")
        print(
            f"  submit to running (warm mirror): {s['submit_to_running_s']:.3f} s"
            f"  (resolving the ref alone: {s['resolve_s']:.3f} s)"
            + ("  ok" if s["submit_to_running_s"] < 2 else "  OVER 2 s")
        )
        print(
            "  trials per minute, 2 s maze episodes:"
            f" 1 worker {s['trials_per_minute_1_workers']:.1f},"
            f" 2 workers {s['trials_per_minute_2_workers']:.1f} ({s['speedup_2_workers']:.2f}x)"
        )


def bench_postgres(admin_url: str, n: int, repeat: int, rng: random.Random) -> dict[str, Any]:
    name = f"labd_bench_{os.getpid()}"
    admin = sa.create_engine(admin_url, isolation_level="AUTOCOMMIT")
    with admin.connect() as db:
        db.execute(sa.text(f'DROP DATABASE IF EXISTS "{name}"'))
        db.execute(sa.text(f'CREATE DATABASE "{name}"'))
    try:
        return bench_index(admin_url.rsplit("/", 1)[0] + "/" + name, n, repeat, rng)
    finally:
        with admin.connect() as db:
            db.execute(sa.text(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)'))
        admin.dispose()


if __name__ == "__main__":
    sys.exit(main())
