"""The web pages: server time at scale, and a trial's record in a real browser.

1. **Server time of the pages over 100,000 synthetic trials** (SQLite, and PostgreSQL
   when ``LABD_TEST_POSTGRES_URL`` is set): p50 and p95 of ``/``, ``/trials`` (filtered
   by outcome and task, its second page), ``/trials/{id}`` and ``/commits/{sha}``,
   rendered by the lab's app in this process (no network), against the JSON of one
   trial (``/api/trials/{id}``) measured in the same run. Target: p95 under 100 ms.
2. **A 5-minute maze trial with its camera, in headless Chromium**: the trial is run by
   the real lab (``labd run``: the sandbox, the bridge, the recorder; a controller that
   drives 3,000 ticks at 10 Hz while it watches the camera), filed in an archive with
   its summary made as a worker makes it, and its page opened in Debian's Chromium
   (Playwright, software WebGL), a fresh browser context each time. Measured: the time
   from navigation to the plots drawn and the first camera frame shown (target: under
   1.5 s), to the 3D scene; and the bytes the page received, all of them and the
   summary alone, against the MCAP's size (target: under a tenth). Baseline: the same
   browser downloading the MCAP itself, as a viewer of the raw record would.

    .venv/bin/python bench/web.py [--records 100000] [--repeat 200] [--runs 5] [--json]
        [--record DIR]   (reuse a trial folder made by an earlier run: --keep DIR)
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
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import sqlalchemy as sa
import uvicorn
from playwright.sync_api import sync_playwright

sys.path[:0] = [str(Path(__file__).resolve().parent), str(Path(__file__).resolve().parents[1])]
from archive import pct, synthetic  # noqa: E402  (bench/archive.py)

from labd.service import Service, ServiceConfig  # noqa: E402
from labd.web import create_app  # noqa: E402
from repository.index import Derived, Filters  # noqa: E402
from repository.manifest import Manifest  # noqa: E402
from repository.trial import Filing, Order, Outcome  # noqa: E402
from repository.well_known import SUMMARY, SUMMARY_MEDIA_TYPE  # noqa: E402
from tests.integration.browser import CHROMIUM, FLAGS  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
SCREENSHOT = ROOT / "docs" / "img" / "trial-page.png"
CONTROLLER = '''\
"""Wander the maze for 5 minutes, watching the camera: ahead until a bumper, then turn."""
from controllers.client import EpisodeOver, Lab

with Lab.connect() as lab:
    lab.subscribe("/camera/image/compressed", "sensor_msgs/msg/CompressedImage")
    bumper = lab.subscribe("/bumper", "lab_msgs/msg/Bumper")
    turning = 0
    try:
        while True:
            b = bumper.latest
            if b and (b["left"] or b["right"]):
                turning = 12
            if turning:
                turning -= 1
                cmd = {"linear": {"x": -0.05}, "angular": {"z": 1.5}}
            else:
                cmd = {"linear": {"x": 0.4}, "angular": {"z": 0.0}}
            lab.publish("/cmd_vel", "geometry_msgs/msg/Twist", cmd)
            lab.step()
    except EpisodeOver:
        pass
'''


# -- 1. server time ----------------------------------------------------------------------


def load(service: Service, n: int, rng: random.Random) -> tuple[list[dict[str, Any]], float]:
    rows = synthetic(n, rng)
    t = time.perf_counter()
    for start in range(0, n, 5000):
        service.index.bulk_insert(rows[start : start + 5000])
    return rows, time.perf_counter() - t


async def bench_pages(
    service: Service, rows: list[dict[str, Any]], repeat: int, rng: random.Random
) -> dict[str, Any]:
    n = len(rows)
    commits = [r["commit"] for r in rows]
    filters = Filters(outcome=Outcome.SUCCESS, task="icreate-maze")
    cursor = service.index.find(filters, limit=50).next
    second = f"/trials?outcome=success&task=icreate-maze&before={cursor}"
    pages = {
        "baseline: /api/trials/{id} (JSON)": lambda: f"/api/trials/{rng.randrange(1, n)}",
        "/": lambda: "/",
        "/trials (filtered, 2nd page)": lambda: second,
        "/trials/{id}": lambda: f"/trials/{rng.randrange(1, n)}",
        "/commits/{sha}": lambda: f"/commits/{rng.choice(commits)}",
    }
    transport = httpx.ASGITransport(app=create_app(service))
    results: dict[str, Any] = {}
    async with httpx.AsyncClient(transport=transport, base_url="http://lab.bench") as client:
        for name, path in pages.items():
            (await client.get(path())).raise_for_status()  # warm
            times = []
            for _ in range(repeat):
                target = path()
                t = time.perf_counter()
                response = await client.get(target)
                times.append((time.perf_counter() - t) * 1000)
                if response.status_code != 200:
                    raise SystemExit(f"{target}: {response.status_code}")
            results[name] = {"p50_ms": statistics.median(times), "p95_ms": pct(times, 95)}
    base = results["baseline: /api/trials/{id} (JSON)"]["p95_ms"]
    for value in results.values():
        value["p95_ratio"] = value["p95_ms"] / base
    return results


def bench_database(
    url: str | None, folder: Path, n: int, repeat: int, rng: random.Random
) -> dict[str, Any]:
    service = Service(ServiceConfig(data=folder, database=url, workers=0))
    try:
        rows, seconds = load(service, n, rng)
        pages = asyncio.run(bench_pages(service, rows, repeat, rng))
    finally:
        service.index.close()
    return {"records": n, "load_seconds": seconds, "pages": pages}


@contextmanager
def postgres_database(admin_url: str) -> Iterator[str]:
    name = f"labd_bench_web_{os.getpid()}"
    admin = sa.create_engine(admin_url, isolation_level="AUTOCOMMIT")
    with admin.connect() as db:
        db.execute(sa.text(f'DROP DATABASE IF EXISTS "{name}"'))
        db.execute(sa.text(f'CREATE DATABASE "{name}"'))
    try:
        yield admin_url.rsplit("/", 1)[0] + "/" + name
    finally:
        with admin.connect() as db:
            db.execute(sa.text(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)'))
        admin.dispose()


# -- 2. a trial's page in a browser ------------------------------------------------------


def make_trial(folder: Path) -> tuple[Path, float]:
    """A 5-minute maze trial with its camera, run by the real lab (``labd run``)."""
    repo = folder / "controller"
    repo.mkdir(parents=True)
    (repo / "lab.toml").write_text(
        '[controller]\ncommand = ["python", "controller.py"]\ntask = "icreate-maze"\n'
    )
    (repo / "controller.py").write_text(CONTROLLER)
    out = folder / "trial"
    t = time.perf_counter()
    done = subprocess.run(
        [sys.executable, "-m", "labd", "run", str(repo), "--param", "time_limit=300",
         "--sandbox", "bwrap", "--out", str(out), "--json"],
        capture_output=True, text=True, check=False,
    )  # fmt: skip
    result = json.loads(done.stdout)
    if result.get("status") != "finished" or result["metrics"]["ticks"] != 3000:
        raise SystemExit(f"the trial did not run its 5 minutes: {done.stdout}\n{done.stderr}")
    return out, time.perf_counter() - t


def file_trial(service: Service, out: Path) -> tuple[int, float]:
    """File the trial as a worker does, its summary made and kept beside it."""
    result = json.loads((out / "result.json").read_text())
    manifest = Manifest.from_json(result["manifest"])
    service.index.add_user("bench", max_running=5)
    user = service.index.user("bench")
    order = Order(
        repository="https://example.org/bench/maze.git", ref="main", commit="b" * 40,
        task="icreate-maze", params=manifest.parameters, seed=manifest.seed, public=True,
    )  # fmt: skip
    trial_id = service.queue.submit(user, order)
    service.queue.claim("bench")
    mcap = out / "trial.mcap"
    filing = Filing(
        status="finished", outcome=result["outcome"], reason=result["reason"],
        mcap=service.store.put_file(mcap), mcap_size=mcap.stat().st_size,
        data_digest=result["data_digest"], manifest=result["manifest"], metrics=result["metrics"],
        backend=result["backend"], wall_seconds=result["wall_seconds"],
    )  # fmt: skip
    service.queue.finish(trial_id, "bench", filing)
    t = time.perf_counter()
    blob = service.host.summarize(mcap, seconds=120)
    seconds = time.perf_counter() - t
    path = out / SUMMARY
    path.write_bytes(blob)
    digest = service.store.put_file(path)
    service.index.put_derived(trial_id, Derived(SUMMARY, digest, len(blob), SUMMARY_MEDIA_TYPE))
    return trial_id, seconds


@contextmanager
def serving(service: Service) -> Iterator[str]:
    server = uvicorn.Server(
        uvicorn.Config(create_app(service), host="127.0.0.1", port=0, log_level="warning")
    )
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    while not server.started:
        thread.join(0.02)
    yield f"http://127.0.0.1:{server.servers[0].sockets[0].getsockname()[1]}"
    server.should_exit = True
    thread.join(10)


@dataclass
class Load:
    """One load of a page: when its parts were drawn, what it received (bytes by URL)."""

    drawn: dict[str, float]
    received: dict[str, int]


def load_page(context: Any, url: str) -> tuple[Any, Load]:
    page = context.new_page()
    cdp = context.new_cdp_session(page)
    cdp.send("Network.enable")
    urls: dict[str, str] = {}
    sizes: dict[str, int] = {}
    errors: list[str] = []
    cdp.on(
        "Network.requestWillBeSent", lambda e: urls.__setitem__(e["requestId"], e["request"]["url"])
    )
    cdp.on(
        "Network.loadingFinished",
        lambda e: sizes.__setitem__(e["requestId"], int(e["encodedDataLength"])),
    )
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.goto(url)
    page.wait_for_function(  # a function: the page's CSP refuses eval (labd/web/headers.py)
        "() => (document.getElementById('record').dataset.drawn || '').includes('scene')",
        timeout=60_000,
    )
    drawn = page.evaluate("window.labRecord.drawn")
    page.wait_for_load_state("networkidle")
    if errors:
        raise SystemExit(f"the page failed: {errors}")
    return page, Load(drawn, {urls.get(r, r): n for r, n in sizes.items()})


FETCH = """async u => { const t = performance.now(); const r = await fetch(u);
    const n = (await r.arrayBuffer()).byteLength; return [performance.now() - t, n]; }"""


def bench_browser(base: str, trial_id: int, runs: int, mcap_size: int) -> dict[str, Any]:
    loads: list[Load] = []
    with sync_playwright() as playwright:
        browser = playwright.chromium.launch(executable_path=CHROMIUM, args=FLAGS)
        for run in range(runs + 1):  # the first run warms the server and Chromium
            context = browser.new_context(viewport={"width": 1280, "height": 900})
            page, load = load_page(context, f"{base}/trials/{trial_id}")
            if run:
                loads.append(load)
            if run == runs:
                page.evaluate("window.labRecord.seek(window.labRecord.summary.duration * 0.42)")
                page.wait_for_timeout(300)
                SCREENSHOT.parent.mkdir(parents=True, exist_ok=True)
                clip = {"x": 0, "y": 0, "width": 1280, "height": 1000}
                page.screenshot(path=str(SCREENSHOT), clip=clip)
                baseline = page.evaluate(FETCH, f"{base}/api/trials/{trial_id}/data.mcap")
            context.close()
        browser.close()
    first = [max(load.drawn["plots"], load.drawn["camera"]) for load in loads]
    scene = [load.drawn["scene"] for load in loads]
    summary = next(n for u, n in loads[-1].received.items() if u.endswith("/summary"))
    return {
        "runs": runs,
        "mcap_bytes": mcap_size,
        "plots_and_camera_ms": {"p50": statistics.median(first), "max": max(first)},
        "scene_ms": {"p50": statistics.median(scene), "max": max(scene)},
        "page_bytes": statistics.median(sum(load.received.values()) for load in loads),
        "summary_bytes": summary,
        "baseline_mcap_download_ms": baseline[0],
        "baseline_mcap_download_bytes": baseline[1],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--records", type=int, default=100_000)
    parser.add_argument("--repeat", type=int, default=200)
    parser.add_argument("--runs", type=int, default=5)
    parser.add_argument("--record", type=Path, help="a trial folder from an earlier --keep")
    parser.add_argument("--keep", type=Path, help="keep the trial's folder here")
    parser.add_argument("--skip-pages", action="store_true")
    parser.add_argument("--skip-browser", action="store_true")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    rng = random.Random(7)
    report: dict[str, Any] = {}
    with tempfile.TemporaryDirectory(prefix="labd-bench-web-") as tmp:
        folder = Path(tmp)
        if not args.skip_pages:
            report["sqlite"] = bench_database(
                None, folder / "sqlite", args.records, args.repeat, rng
            )
            admin = os.environ.get("LABD_TEST_POSTGRES_URL")
            if admin:
                with postgres_database(admin) as url:
                    report["postgresql"] = bench_database(
                        url, folder / "pg", args.records, args.repeat, rng
                    )
        if not args.skip_browser:
            out = args.record
            if out is None:
                out, seconds = make_trial(args.keep or folder / "made")
                report["trial_seconds"] = seconds
            service = Service(ServiceConfig(data=folder / "browser", workers=0))
            trial_id, report["summary_seconds"] = file_trial(service, out)
            with serving(service) as base:
                report["browser"] = bench_browser(
                    base, trial_id, args.runs, (out / "trial.mcap").stat().st_size
                )
            service.index.close()
    if args.json:
        print(json.dumps(report, indent=2))
        return
    show(report)


def show(report: dict[str, Any]) -> None:
    for db in ("sqlite", "postgresql"):
        if db not in report:
            continue
        r = report[db]
        print(
            f"pages on {db}: {r['records']:,} synthetic trials"
            f" (loaded in {r['load_seconds']:.1f} s), server time:"
        )
        for name, q in r["pages"].items():
            mark = (
                ""
                if name.startswith("baseline")
                else ("  ok" if q["p95_ms"] < 100 else "  OVER 100 ms")
            )
            print(
                f"  {name:<36} p50 {q['p50_ms']:7.2f} ms  p95 {q['p95_ms']:7.2f} ms"
                f"  ({q['p95_ratio']:5.1f}x baseline){mark}"
            )
    if "browser" in report:
        b = report["browser"]
        mb = b["mcap_bytes"]
        if "trial_seconds" in report:
            print(
                "a 5-minute maze trial with its camera:"
                f" run by labd run in {report['trial_seconds']:.0f} s"
            )
        print(
            f"  its MCAP: {mb / 1e6:.2f} MB; its summary made in {report['summary_seconds']:.2f} s"
        )
        first = b["plots_and_camera_ms"]
        print(
            f"  headless Chromium, {b['runs']} fresh loads: plots and first camera frame"
            f" p50 {first['p50']:.0f} ms, max {first['max']:.0f} ms"
            + ("  ok" if first["max"] < 1500 else "  OVER 1.5 s")
        )
        print(
            f"  3D scene drawn: p50 {b['scene_ms']['p50']:.0f} ms,"
            f" max {b['scene_ms']['max']:.0f} ms"
        )
        print(
            f"  bytes received by the page: {b['page_bytes'] / 1e3:.0f} kB"
            f" ({b['page_bytes'] / mb:.3f} of the MCAP)"
            + ("  ok" if b["page_bytes"] < mb / 10 else "  OVER a tenth")
            + f"; the summary alone {b['summary_bytes'] / 1e3:.0f} kB"
            + f" ({b['summary_bytes'] / mb:.3f})"
        )
        print(
            f"  baseline: the browser downloading the MCAP itself:"
            f" {b['baseline_mcap_download_ms']:.0f} ms,"
            f" {b['baseline_mcap_download_bytes'] / 1e6:.2f} MB"
        )
        print(f"  screenshot: {SCREENSHOT.relative_to(ROOT)}")


if __name__ == "__main__":
    sys.exit(main())
