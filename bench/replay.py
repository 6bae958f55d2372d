"""Replay against the trial it replays: how much faster a record is checked than made.

For each example controller (the maze and the PR2), one trial runs through the trial
runner in bubblewrap: its running time (first ``/lab/step`` to its end) and its whole
time (check-out, sandbox, run, record). Then its record is replayed (``labd.replay``,
with the lab's type registry already loaded, as in a worker): without rendering, and
rendering the task's camera to MP4 at 320x240 and at 640x480 (every tick, H.264). Each
figure is the median of ``--repeat`` replays; the ratios are the trial's times over the
replay's (target: at least 2 without rendering: no controller, no bridge, no sandbox).

    .venv/bin/python bench/replay.py [--repeat 3] [--json]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

import sandbox
from labd.graph.types import TypeRegistry
from labd.replay import replay
from labd.trial import LabHost, client_library
from labd.video import Video, VideoSpec
from repository.trial import Order, Outcome
from scheduler.runner import RunOptions, run_trial

ROOT = Path(__file__).resolve().parent.parent
EXAMPLES = {
    "icreate-maze": (ROOT / "controllers" / "examples" / "icreate-maze", "front"),
    "pr2-table": (ROOT / "controllers" / "examples" / "pr2-pick-place", "head"),
}
TARGET = 2.0


def trial(example: Path, out: Path, cache: Path) -> Any:
    backend = sandbox.backend("bwrap", cache, extra_packages=[client_library()])
    result = asyncio.run(
        run_trial(
            Order(repository=str(example), seed=1),
            backend=backend,
            host=LabHost(),
            out=out,
            cache=cache,
            options=RunOptions(),
        )
    )
    if result.outcome is not Outcome.SUCCESS:
        raise SystemExit(f"{example.name}: {result.outcome}: {result.reason}")
    return result


def timed(
    record: Path, camera: str | None, size: str, folder: Path, repeat: int, types: TypeRegistry
) -> float:
    seconds = []
    for n in range(repeat):
        videos = (
            []
            if camera is None
            else [Video(VideoSpec.parse(camera, size, 120), folder / f"{n}.mp4")]
        )
        start = time.perf_counter()
        verdict = replay(record, types, renderers=videos)
        for video in videos:
            video.close()
        seconds.append(time.perf_counter() - start)
        if not verdict.verified:
            raise SystemExit(f"{record}: {verdict}")
    return statistics.median(seconds)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--cache", type=Path, default=ROOT / "lab-data" / "cache")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    report: dict[str, Any] = {}
    types = TypeRegistry.default()
    with tempfile.TemporaryDirectory(prefix="labd-bench-replay-") as folder:
        work = Path(folder)
        for task, (example, camera) in EXAMPLES.items():
            result = trial(example, work / task, args.cache.resolve())
            record = result.mcap
            assert record is not None and result.run_seconds is not None
            figures = {
                "ticks": result.metrics["ticks"],
                "trial_s": result.run_seconds,
                "trial_whole_s": result.wall_seconds,
            }
            for label, cam, size in (
                ("replay_s", None, ""),
                ("replay_320x240_s", camera, "320x240"),
                ("replay_640x480_s", camera, "640x480"),
            ):
                figures[label] = timed(record, cam, size, work, args.repeat, types)
                figures[label.replace("_s", "_ratio")] = result.run_seconds / figures[label]
            figures["replay_whole_ratio"] = result.wall_seconds / figures["replay_s"]
            report[task] = figures
    if args.json:
        print(json.dumps(report, indent=2))
        return
    print(f"{'task':<14} {'ticks':>6} {'trial run/whole':>16} {'replay':>8} {'ratio':>11}"
          f" {'+320x240':>9} {'ratio':>6} {'+640x480':>9} {'ratio':>6}")  # fmt: skip
    for task, f in report.items():
        mark = "ok" if f["replay_ratio"] >= TARGET else f"UNDER {TARGET} (of the run)"
        print(
            f"{task:<14} {f['ticks']:>6} {f['trial_s']:>7.2f}s/{f['trial_whole_s']:>6.2f}s"
            f" {f['replay_s']:>7.2f}s {f['replay_ratio']:>4.1f}x/{f['replay_whole_ratio']:>4.1f}x"
            f" {f['replay_320x240_s']:>8.2f}s"
            f" {f['replay_320x240_ratio']:>5.1f}x {f['replay_640x480_s']:>8.2f}s"
            f" {f['replay_640x480_ratio']:>5.1f}x  {mark}"
        )


if __name__ == "__main__":
    main()
