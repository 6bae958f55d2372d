"""Run by the real ``lerobot`` package's Python (tests/integration/test_lerobot.py): load
labd's LeRobot exports, merge them with ``aggregate_datasets``, and print what came out.

    python lerobot_check.py MERGED A,B[,...] [DATASET ...]

Loads every dataset named (those of the comma-separated list and the others), merges the
list's into MERGED with ``aggregate_datasets`` and loads that too. Prints one JSON
object: for each dataset and for the merge, the frames, episodes, an item's keys and
image shape, each episode's ``labd/trial`` and provenance, and the seconds it took.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

from lerobot.datasets.aggregate import aggregate_datasets
from lerobot.datasets.lerobot_dataset import LeRobotDataset


def load(root: Path, repo_id: str) -> dict:
    started = time.perf_counter()
    dataset = LeRobotDataset(repo_id, root=root, video_backend="pyav")
    item = dataset[len(dataset) - 1]
    episodes = dataset.meta.episodes
    trials = [int(t) for t in episodes["labd/trial"]]
    provenance = [json.loads(p) for p in episodes["labd/provenance"]]
    return {
        "frames": len(dataset),
        "episodes": dataset.num_episodes,
        "keys": sorted(item),
        "image": list(item["observation.images.camera"].shape),
        "state": list(item["observation.state"].shape),
        "task": item["task"],
        "trials": trials,
        "commits": [p.get("commit") for p in provenance],
        "data_digests": [p.get("data_digest") for p in provenance],
        "seconds": round(time.perf_counter() - started, 2),
    }


def main() -> None:
    out = Path(sys.argv[1])
    merged = [Path(p) for p in sys.argv[2].split(",")]
    roots = merged + [Path(p) for p in sys.argv[3:]]
    report: dict = {"datasets": {root.name: load(root, f"labd/{root.name}") for root in roots}}
    started = time.perf_counter()
    ids = [f"labd/{root.name}" for root in merged]
    aggregate_datasets(ids, "labd/merged", roots=merged, aggr_root=out)
    report["aggregate_seconds"] = round(time.perf_counter() - started, 2)
    report["merged"] = load(out, "labd/merged")
    print(json.dumps(report))


if __name__ == "__main__":
    main()
