"""Episodes (``repository.export``) as a LeRobot v3.0 dataset, cameras as AV1 video.

The folder, as LeRobot 0.4 and later write and read it:

    meta/info.json                       codebase_version v3.0, fps, features, totals, paths
    meta/stats.json                      per feature: min, max, mean, std, count, quantiles
    meta/tasks.parquet                   the instructions (task_index, indexed by task)
    meta/episodes/chunk-000/file-000.parquet
                                         one row per episode: length, where its rows and
                                         video frames are, its statistics, and its
                                         provenance under ``labd/...`` (below)
    data/chunk-000/file-000.parquet      one row per tick: observation.state, action,
                                         next.reward, next.done, next.success, timestamp,
                                         frame_index, episode_index, index, task_index
    videos/observation.images.<camera>/chunk-000/file-000.mp4
                                         every episode's frames, one after the other

**Provenance.** Each episode's row of ``meta/episodes`` carries where it came from in
columns of its own: ``labd/trial``, ``labd/kind``, ``labd/repository``,
``labd/commit``, ``labd/manifest_digest``, ``labd/data_digest``, ``labd/seed``,
``labd/outcome`` and ``labd/provenance`` (all of it as JSON, the lab's signature of the
record included). That is where LeRobot keeps per-episode metadata, so it survives
``aggregate_datasets`` and loading; nothing is added to ``info.json``, whose unknown
fields newer LeRobot drops. The export's own description (its layout, the lab's
version) is ``meta/labd.json``, which LeRobot does not read.

**Video.** Frames are the JPEG images of the episodes, decoded and encoded as LeRobot
encodes them (PyAV's FFmpeg: ``libsvtav1``, ``yuv420p``, a keyframe every 2 frames,
CRF 30), one file per camera, an episode's frames from ``from_timestamp`` to
``to_timestamp``. PyAV is imported only when a video is encoded: it is slow to load, and
a dataset without cameras (``labd.exports.write_dataset``) needs none.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Sequence
from fractions import Fraction
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa  # type: ignore[import-untyped]
import pyarrow.parquet as pq  # type: ignore[import-untyped]
import simplejpeg

from repository.errors import ExportError
from repository.export import IMAGES, Episode, ExportFormat, Layout

VERSION = "v3.0"
CHUNKS_SIZE = 1000  # LeRobot's defaults, recorded in info.json
DATA_FILE_MB = 100
VIDEO_FILE_MB = 200
DATA_PATH = "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
VIDEO_PATH = "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4"
EPISODES_PATH = "meta/episodes/chunk-000/file-000.parquet"
INFO_PATH = "meta/info.json"
QUANTILES = {"q01": 0.01, "q10": 0.10, "q50": 0.50, "q90": 0.90, "q99": 0.99}
CODEC, PIX_FMT, GOP, CRF = "libsvtav1", "yuv420p", 2, 30
PROVENANCE_FIELDS = (
    "trial",
    "kind",
    "repository",
    "commit",
    "manifest_digest",
    "data_digest",
    "seed",
    "outcome",
)


def write_lerobot(episodes: Sequence[Episode], layout: Layout, folder: Path) -> list[Path]:
    """Write ``episodes`` as a LeRobot v3.0 dataset in ``folder``; the files written."""
    fps = frames_per_second(episodes)
    instructions = list(dict.fromkeys(e.instruction for e in episodes))
    task_of = {text: i for i, text in enumerate(instructions)}
    lengths = [len(e) for e in episodes]
    starts = np.cumsum([0, *lengths])
    state = np.array([row for e in episodes for row in e.state], np.float32)
    action = np.array([row for e in episodes for row in e.action], np.float32)
    data: dict[str, np.ndarray] = {
        "observation.state": state.reshape(len(state), len(layout.observation)),
        "action": action.reshape(len(action), len(layout.action)),
        "next.reward": np.array([r for e in episodes for r in e.reward], np.float32),
        "next.done": np.array([d for e in episodes for d in e.done], np.bool_),
        "next.success": np.array([s for e in episodes for s in e.success], np.bool_),
        "timestamp": np.array([t / fps for e in episodes for t in e.ticks], np.float32),
        "frame_index": np.array([t for e in episodes for t in e.ticks], np.int64),
        "episode_index": np.repeat(np.arange(len(episodes), dtype=np.int64), lengths),
        "index": np.arange(int(starts[-1]), dtype=np.int64),
        "task_index": np.repeat(
            np.array([task_of[e.instruction] for e in episodes], np.int64), lengths
        ),
    }
    features: dict[str, dict[str, Any]] = {}
    for key, value in data.items():
        shape = [int(value.shape[1])] if value.ndim == 2 else [1]
        features[key] = {"dtype": str(value.dtype), "shape": shape, "names": None}
    features["observation.state"]["names"] = [e.name for e in layout.observation]
    features["action"]["names"] = [e.name for e in layout.action]
    paths = {
        "info": folder / INFO_PATH,
        "stats": folder / "meta" / "stats.json",
        "tasks": folder / "meta" / "tasks.parquet",
        "episodes": folder / EPISODES_PATH,
        "data": folder / DATA_PATH.format(chunk_index=0, file_index=0),
        "labd": folder / "meta" / "labd.json",
    }
    for path in paths.values():
        path.parent.mkdir(parents=True, exist_ok=True)
    pq.write_table(pa.table({k: _arrow(v) for k, v in data.items()}), paths["data"])
    files = list(paths.values())

    stats: dict[str, dict[str, Any]] = {key: _stats(value) for key, value in data.items()}
    per_episode: list[dict[str, Any]] = [{} for _ in episodes]
    for camera in layout.cameras:
        key = IMAGES + camera.name
        video = folder / VIDEO_PATH.format(video_key=key, chunk_index=0, file_index=0)
        frame, image_stats, episode_stats = _encode(episodes, camera.name, video, fps)
        files.append(video)
        features[key] = {
            "dtype": "video",
            "shape": list(frame),
            "names": ["height", "width", "channels"],
            "info": {
                "video.height": frame[0],
                "video.width": frame[1],
                "video.codec": "av1",
                "video.pix_fmt": PIX_FMT,
                "video.is_depth_map": False,
                "video.fps": fps,
                "video.channels": 3,
                "has_audio": False,
            },
        }
        stats[key] = image_stats
        for i, episode in enumerate(episodes):
            where_video = per_episode[i]
            where_video[f"videos/{key}/chunk_index"] = 0
            where_video[f"videos/{key}/file_index"] = 0
            where_video[f"videos/{key}/from_timestamp"] = float(starts[i]) / fps
            where_video[f"videos/{key}/to_timestamp"] = float(starts[i] + len(episode)) / fps
            for stat, figure in episode_stats[i].items():
                where_video[f"stats/{key}/{stat}"] = figure

    rows: list[dict[str, Any]] = []
    for i, episode in enumerate(episodes):
        where = slice(int(starts[i]), int(starts[i + 1]))
        row: dict[str, Any] = {
            "episode_index": i,
            "tasks": [episode.instruction],
            "length": len(episode),
            "data/chunk_index": 0,
            "data/file_index": 0,
            "dataset_from_index": int(starts[i]),
            "dataset_to_index": int(starts[i + 1]),
            **per_episode[i],
            "meta/episodes/chunk_index": 0,
            "meta/episodes/file_index": 0,
        }
        for feature, values in data.items():
            for stat, figures in _stats(values[where]).items():
                row[f"stats/{feature}/{stat}"] = figures
        provenance = episode.provenance
        for name in PROVENANCE_FIELDS:
            row[f"labd/{name}"] = provenance.get(name)
        row["labd/provenance"] = json.dumps(provenance, sort_keys=True, ensure_ascii=False)
        rows.append(row)
    pq.write_table(_episodes_table(rows), paths["episodes"])
    pq.write_table(_tasks_table(instructions), paths["tasks"])
    paths["stats"].write_text(json.dumps(stats, indent=2))
    info = {
        "codebase_version": VERSION,
        "robot_type": layout.task,
        "fps": fps,
        "total_episodes": len(episodes),
        "total_frames": int(starts[-1]),
        "total_tasks": len(instructions),
        "chunks_size": CHUNKS_SIZE,
        "data_files_size_in_mb": DATA_FILE_MB,
        "video_files_size_in_mb": VIDEO_FILE_MB,
        "data_path": DATA_PATH,
        "video_path": VIDEO_PATH if layout.cameras else None,
        "splits": {"train": f"0:{len(episodes)}"},
        "features": features,
    }
    paths["info"].write_text(json.dumps(info, indent=2, ensure_ascii=False))
    paths["labd"].write_text(
        json.dumps(
            {"layout": layout.describe(), "episodes": [e.provenance for e in episodes]},
            indent=2,
            sort_keys=True,
        )
    )
    return files


def frames_per_second(episodes: Sequence[Episode]) -> int:
    """The control rate: LeRobot needs evenly spaced frames, a whole number a second."""
    steps = {b - a for e in episodes for a, b in zip(e.times, e.times[1:], strict=False)}
    if not steps:
        raise ExportError("LeRobot needs at least two ticks in some episode to know its rate")
    if len(steps) != 1 or min(steps) <= 0:
        raise ExportError("LeRobot needs evenly spaced frames; these records' ticks are not")
    fps = 1e9 / steps.pop()
    if not math.isclose(fps, round(fps), abs_tol=1e-6):
        raise ExportError(f"LeRobot needs a whole number of frames per second, not {fps:g}")
    return round(fps)


def _encode(
    episodes: Sequence[Episode], camera: str, path: Path, fps: int
) -> tuple[tuple[int, int, int], dict[str, Any], list[dict[str, Any]]]:
    """Encode every episode's frames of ``camera`` into one AV1 MP4; its frame shape, and
    LeRobot's image statistics (per channel, in [0, 1]) overall and per episode."""
    import av  # noqa: PLC0415 (slow to load: only where a video is made)

    path.parent.mkdir(parents=True, exist_ok=True)
    # SVT-AV1 prints its configuration to stderr unless told to log errors only.
    os.environ.setdefault("SVT_LOG", "1")
    shape: tuple[int, int, int] | None = None
    container = av.open(str(path), mode="w", format="mp4")
    overall: list[np.ndarray] = []
    per_episode: list[dict[str, Any]] = []
    try:
        stream: Any = None
        for episode in episodes:
            sample: list[np.ndarray] = []
            for n, jpeg in enumerate(episode.images[camera]):
                assert jpeg is not None  # export filled every image
                pixels = simplejpeg.decode_jpeg(jpeg, colorspace="RGB")
                if shape is None:
                    shape = (int(pixels.shape[0]), int(pixels.shape[1]), 3)
                    stream = container.add_stream(CODEC, rate=Fraction(fps))
                    stream.width, stream.height = shape[1], shape[0]
                    stream.pix_fmt = PIX_FMT
                    stream.options = {"g": str(GOP), "crf": str(CRF)}
                elif pixels.shape != shape:
                    raise ExportError(
                        f"{camera}'s images are not all {shape[1]}x{shape[0]} (one is"
                        f" {pixels.shape[1]}x{pixels.shape[0]}): one video needs one size"
                    )
                frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(pixels), format="rgb24")
                for packet in stream.encode(frame):
                    container.mux(packet)
                if n % max(1, len(episode) // 50) == 0:  # LeRobot samples frames too
                    sample.append(pixels[::4, ::4])
            frames = np.stack(sample)
            per_episode.append(_image_stats(frames))
            overall.append(frames)
        if stream is not None:
            for packet in stream.encode():
                container.mux(packet)
    finally:
        container.close()
    assert shape is not None
    return shape, _image_stats(np.concatenate(overall)), per_episode


def _image_stats(frames: np.ndarray) -> dict[str, Any]:
    """LeRobot's statistics of images: per channel, over pixels and frames, in [0, 1],
    each shaped (3, 1, 1)."""
    values = frames.reshape(-1, 3).astype(np.float64) / 255.0
    out: dict[str, Any] = {
        "min": values.min(axis=0),
        "max": values.max(axis=0),
        "mean": values.mean(axis=0),
        "std": values.std(axis=0),
    }
    for key, q in QUANTILES.items():
        out[key] = np.quantile(values, q, axis=0)
    stats: dict[str, Any] = {k: v.reshape(3, 1, 1).tolist() for k, v in out.items()}
    stats["count"] = [len(frames)]
    return stats


def _stats(values: np.ndarray) -> dict[str, list[float] | list[int]]:
    """LeRobot's statistics of one feature: per entry, over frames."""
    data = values.reshape(len(values), -1).astype(np.float64)
    stats: dict[str, list[float] | list[int]] = {
        "min": data.min(axis=0).tolist(),
        "max": data.max(axis=0).tolist(),
        "mean": data.mean(axis=0).tolist(),
        "std": data.std(axis=0).tolist(),
        "count": [len(data)],
    }
    for key, q in QUANTILES.items():
        stats[key] = np.quantile(data, q, axis=0).tolist()
    return stats


def _arrow(values: np.ndarray) -> pa.Array:
    """A column as LeRobot's ``datasets`` writes it: vectors as fixed-size lists."""
    if values.ndim == 2:
        return pa.FixedSizeListArray.from_arrays(pa.array(values.reshape(-1)), values.shape[1])
    return pa.array(values)


def _episodes_table(rows: list[dict[str, Any]]) -> pa.Table:
    """``meta/episodes``: the provenance columns typed even where every value is None."""
    table = pa.Table.from_pylist(rows)
    fields = []
    for f in table.schema:
        if pa.types.is_null(f.type):
            fields.append(pa.field(f.name, pa.string()))
        else:
            fields.append(f)
    return table.cast(pa.schema(fields))


def _tasks_table(tasks: Sequence[str]) -> pa.Table:
    """``meta/tasks.parquet`` as pandas writes LeRobot's: ``task_index``, indexed by ``task``."""
    table = pa.table({"task_index": pa.array(range(len(tasks)), pa.int64()), "task": list(tasks)})
    pandas = {
        "index_columns": ["task"],
        "column_indexes": [_pandas_column(None, "unicode", "object", {"encoding": "UTF-8"})],
        "columns": [
            _pandas_column("task_index", "int64", "int64"),
            _pandas_column("task", "unicode", "object"),
        ],
        "creator": {"library": "pyarrow", "version": pa.__version__},
    }
    return table.replace_schema_metadata({"pandas": json.dumps(pandas)})


def _pandas_column(
    name: str | None, pandas_type: str, numpy_type: str, metadata: Any = None
) -> dict[str, Any]:
    return {
        "name": name,
        "field_name": name,
        "pandas_type": pandas_type,
        "numpy_type": numpy_type,
        "metadata": metadata,
    }


def frames(folder: Path) -> int:
    """The rows of the dataset in ``folder``, as its ``info.json`` counts them."""
    return int(json.loads((folder / INFO_PATH).read_text())["total_frames"])


def episodes(folder: Path) -> int:
    """The episodes of the dataset in ``folder``, as its ``info.json`` counts them."""
    return int(json.loads((folder / INFO_PATH).read_text())["total_episodes"])


LEROBOT = ExportFormat(
    name="lerobot",
    title="LeRobot (zip)",
    doc="a LeRobot v3.0 dataset, as a zip of its folder",
    media_type="application/zip",
    suffix="-lerobot.zip",
    served=None,
    write=write_lerobot,
    frames=frames,
    episodes=episodes,
)
