"""Episodes (``repository.export``) as one Parquet file: ``data.parquet``, a row per tick.

Its columns are the rows' indices, time and instruction, ``next.reward``,
``next.done`` and ``next.success``, one float32 column per entry of the task's layout
(``observation.<name>``, ``action.<name>``) and one binary column of JPEG images per
camera (``observation.images.<camera>``), zstd-compressed; docs/service.md lists them.
The file's metadata holds each episode's provenance (``labd.episodes``) and the layout
(``labd.layout``).
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pyarrow as pa  # type: ignore[import-untyped]
import pyarrow.parquet as pq  # type: ignore[import-untyped]

from repository.export import IMAGES, Episode, ExportFormat, Layout
from repository.well_known import PARQUET_FILE

FILE = PARQUET_FILE
EPISODES_KEY = "labd.episodes"  # the file's metadata: each episode's provenance
LAYOUT_KEY = "labd.layout"


def columns(episodes: Sequence[Episode], layout: Layout) -> dict[str, pa.Array]:
    """The rows as columns: indices, time, instruction, next.*, the vectors' entries."""
    state = _matrix([e.state for e in episodes], len(layout.observation))
    action = _matrix([e.action for e in episodes], len(layout.action))
    out: dict[str, pa.Array] = {
        "index": pa.array(range(len(state)), pa.int64()),
        "episode_index": pa.array([i for i, e in enumerate(episodes) for _ in e.ticks], pa.int64()),
        "frame_index": pa.array([t for e in episodes for t in e.ticks], pa.int64()),
        "timestamp": pa.array(
            [(t - e.times[0]) / 1e9 for e in episodes for t in e.times], pa.float32()
        ),
        "trial": pa.array(
            [e.provenance.get("trial") for e in episodes for _ in e.ticks], pa.int64()
        ),
        "task": pa.array([e.instruction for e in episodes for _ in e.ticks], pa.string()),
        "next.reward": pa.array([r for e in episodes for r in e.reward], pa.float32()),
        "next.done": pa.array([d for e in episodes for d in e.done], pa.bool_()),
        "next.success": pa.array([s for e in episodes for s in e.success], pa.bool_()),
    }
    for i, entry in enumerate(layout.observation):
        out[f"observation.{entry.name}"] = pa.array(state[:, i], pa.float32())
    for i, entry in enumerate(layout.action):
        out[f"action.{entry.name}"] = pa.array(action[:, i], pa.float32())
    return out


def _matrix(parts: Sequence[Sequence[Sequence[float]]], width: int) -> np.ndarray:
    rows = [row for part in parts for row in part]
    return np.array(rows, np.float32).reshape(len(rows), width)


def write_parquet(episodes: Sequence[Episode], layout: Layout, folder: Path) -> list[Path]:
    """Write ``episodes`` as ``data.parquet`` in ``folder``; the file written."""
    data = columns(episodes, layout)
    for camera in layout.cameras:
        images = [image for e in episodes for image in e.images[camera.name]]
        data[f"{IMAGES}{camera.name}"] = pa.array(images, pa.binary())
    table = pa.table(data).replace_schema_metadata(
        {
            EPISODES_KEY: json.dumps([e.provenance for e in episodes], sort_keys=True),
            LAYOUT_KEY: json.dumps(layout.describe()),
        }
    )
    path = folder / FILE
    pq.write_table(table, path, compression="zstd")
    return [path]


def frames(folder: Path) -> int:
    """The rows of the export in ``folder``."""
    return int(pq.ParquetFile(folder / FILE).metadata.num_rows)


def episodes(folder: Path) -> int:
    """The episodes of the export in ``folder``, as its metadata lists them."""
    metadata = pq.ParquetFile(folder / FILE).schema_arrow.metadata or {}
    return len(json.loads(metadata.get(EPISODES_KEY.encode(), b"[]")))


PARQUET = ExportFormat(
    name="parquet",
    title="Parquet",
    doc="one Parquet file, a row per control tick",
    media_type="application/vnd.apache.parquet",
    suffix=".parquet",
    served=FILE,
    write=write_parquet,
    frames=frames,
    episodes=episodes,
)
