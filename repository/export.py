"""Observation-action pairs for learning, from a trial's MCAP record: Parquet or LeRobot v3.0.

**Frames.** The lab runs in lockstep: after control tick k it publishes that tick's
observations, then ``/lab/episode`` (tick k); the controller publishes its commands and
calls ``/lab/step``; the lab applies them, advances to tick k+1 and publishes again. The
record keeps that order, and this module reads it in that order (not by log time, since
a tick's commands share its time). Frame k pairs:

- *observation*: on each observation topic, the last message recorded up to
  ``/lab/episode`` tick k. Topics published every tick give tick k's message; those
  published less often or once (``/goal``, ``/tf_static``) give the latest one, which
  the lab latches;
- *action*: on each action topic, the last message received before the step from tick k
  to k+1, which is what the lab's tasks act on: a command is kept until replaced (a
  ``/cmd_vel`` holds its speeds). When the controller published nothing before a step,
  the action is its previous command again;
- *next*: what that step produced, from ``/lab/episode`` tick k+1: ``next.reward``,
  ``next.done`` (the episode ended with it), ``next.success``.

Observations are what the lab published, actions what a client (the controller, a
person's page) published: the recorder names the side of each channel in its metadata
(``labd.side``: ``lab`` or ``client``), and a channel of the other side on a named topic
is not read. Records made before sides were kept are read by topic alone.

An observation with no step after it (an episode's last, or where the record stops)
makes no frame, as no action followed it. Neither do the first ticks, before every
action topic has had a message: the robot then acted on its task's initial state (at
rest), not on a command. Named topics that the record does not hold at all (a camera no
one watched, a command never sent) are left out and listed in the summary. A new
episode in one record (the tick going back) starts a new episode of the export.

**Fields.** Messages are decoded with their own ros2msg schemas (``mcap_ros2``) and
flattened by field path (``pose.pose.position.x``, ``covariance[3]``). A list whose length
is the same in every frame of the record (fixed arrays, and sequences such as the
wheels of a ``JointState``) is flattened element by element, up to ``MAX_FLATTENED``
elements; other lists are variable-length.

- ``parquet``: ``OUT/data.parquet``, one row per frame: ``episode_index``,
  ``frame_index`` (within the episode), ``tick``, ``timestamp`` (simulation seconds),
  ``next.*``, then ``observation.<topic>.<path>`` and ``action.<topic>.<path>``: numbers
  and booleans as such, strings as strings, byte arrays (JPEG images) as binary,
  variable-length lists as JSON text (bytes inside them as base64). The provenance is
  JSON in the schema metadata under ``labd.provenance``.
- ``lerobot``: a LeRobot dataset, codebase v3.0, fps = the control rate:
  ``meta/info.json`` (features, totals, path templates; the provenance under ``labd``),
  ``meta/stats.json``, ``meta/tasks.parquet`` (the task's name), ``meta/episodes/...``
  and ``data/chunk-000/file-000.parquet`` with ``observation.state`` and ``action``: the
  fixed-length numeric fields (booleans as 0/1) of the observation and action topics,
  concatenated as float32, with their names. Time stamps (``builtin_interfaces`` Time
  and Duration) are left out of the vectors: ``timestamp`` carries time, here seconds
  since the episode's first frame. Everything goes in one data file.

**Left out.** Camera images are not in the LeRobot export: v3.0 keeps cameras as MP4
videos, which would need a video encoder here; the Parquet export has the JPEG bytes.
Strings and variable-length fields are not in the LeRobot vectors either.

Errors are ``ExportError``; the output folder appears whole or not at all.
"""

from __future__ import annotations

import base64
import json
import logging
import math
import shutil
import struct
import uuid
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa  # type: ignore[import-untyped]
import pyarrow.parquet as pq  # type: ignore[import-untyped]
from mcap.exceptions import McapError
from mcap.reader import NonSeekingReader
from mcap_ros2.decoder import DecoderFactory
from zstandard import ZstdError

from repository.errors import ExportError

FORMATS = ("parquet", "lerobot")
EPISODE = "/lab/episode"  # lab_msgs/msg/Episode, after each tick's observations
PROVENANCE_KEY = "labd.provenance"
SIDE_KEY = "labd.side"  # channel metadata: which side published (labd.recorder.reader)
PARQUET_NAME = "data.parquet"
MAX_FLATTENED = 256  # longer lists stay whole (JSON), however constant their length
TIME_TYPES = frozenset({"builtin_interfaces/Time", "builtin_interfaces/Duration"})
LEROBOT_VERSION = "v3.0"
CHUNKS_SIZE = 1000  # LeRobot's defaults, recorded in info.json
DATA_FILE_MB = 100
VIDEO_FILE_MB = 200
DATA_PATH = "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
QUANTILES = {"q01": 0.01, "q10": 0.10, "q50": 0.50, "q90": 0.90, "q99": 0.99}
_UNREADABLE = (McapError, OSError, ValueError, EOFError, IndexError, struct.error, ZstdError)

log = logging.getLogger("repository.export")


@dataclass(frozen=True)
class ExportSummary:
    """What an export wrote.

    ``observation_names`` and ``action_names`` are the Parquet columns, or the names of
    the entries of LeRobot's ``observation.state`` and ``action``. ``dropped`` counts
    the recorded ticks that made no frame; ``missing_topics`` the named topics the
    record does not hold.
    """

    format: str
    out: Path
    files: tuple[Path, ...]
    frames: int
    episodes: int
    observation_names: tuple[str, ...]
    action_names: tuple[str, ...]
    missing_topics: tuple[str, ...]
    dropped: int


@dataclass(frozen=True)
class Frame:
    """One observation, the action that followed it, and what the step produced."""

    episode: int
    tick: int
    time_ns: int
    observations: dict[str, Any]  # topic -> decoded message
    actions: dict[str, Any]
    next: Any  # the /lab/episode message after the step
    next_time_ns: int


@dataclass(frozen=True)
class Frames:
    """The frames of a record, with the topics they cover."""

    frames: list[Frame]
    observation_topics: list[str]
    action_topics: list[str]
    missing_topics: list[str]
    ticks: int  # control ticks recorded
    task: str


@dataclass(frozen=True)
class Leaf:
    """One flattened field: its path in the message, what it holds, how to get it."""

    steps: tuple[str | int, ...]
    kind: str  # bool, int, float, string, bytes or json
    stamp: bool  # inside a time stamp

    @property
    def name(self) -> str:
        text = ""
        for step in self.steps:
            text += f"[{step}]" if isinstance(step, int) else f".{step}"
        return text.lstrip(".")

    @property
    def numeric(self) -> bool:
        return self.kind in ("bool", "int", "float")

    def get(self, message: Any) -> Any:
        for step in self.steps:
            message = message[step] if isinstance(step, int) else getattr(message, step)
        return message


def export(
    mcap: Path,
    out: Path,
    fmt: str,
    *,
    observations: Sequence[str],
    actions: Sequence[str],
    provenance: Mapping[str, Any],
) -> ExportSummary:
    """Export the observation-action frames of the record ``mcap`` to the folder ``out``.

    ``fmt`` is ``"parquet"`` or ``"lerobot"``; ``observations`` and ``actions`` name the
    topics (a task's observation and command topics); ``provenance`` is JSON the export
    carries (the trial's manifest and digests, repository, commit ...). ``out`` must not
    exist or be an empty folder. ExportError for what cannot be exported.
    """
    if fmt not in FORMATS:
        raise ExportError(f"unknown format {fmt!r}: the formats are {', '.join(FORMATS)}")
    try:
        provenance_text = json.dumps(
            dict(provenance), sort_keys=True, ensure_ascii=False, allow_nan=False
        )
    except (TypeError, ValueError) as err:
        raise ExportError(f"the provenance must be JSON: {err}") from None
    if not observations or not actions:
        raise ExportError("name at least one observation topic and one action topic")
    out = Path(out)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise ExportError(f"{out} already exists: give a new or empty folder")
    frames = read_frames(Path(mcap), observations, actions)
    tmp = out.parent / f".{out.name}.{uuid.uuid4().hex}.tmp"
    tmp.mkdir(parents=True)
    try:
        if fmt == "parquet":
            files, obs_names, act_names = _write_parquet(frames, tmp, provenance_text)
        else:
            files, obs_names, act_names = _write_lerobot(frames, tmp, json.loads(provenance_text))
        if out.exists():
            out.rmdir()
        tmp.rename(out)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)  # gone already unless something failed
    summary = ExportSummary(
        format=fmt,
        out=out,
        files=tuple(out / f.relative_to(tmp) for f in files),
        frames=len(frames.frames),
        episodes=len({f.episode for f in frames.frames}),
        observation_names=tuple(obs_names),
        action_names=tuple(act_names),
        missing_topics=tuple(frames.missing_topics),
        dropped=frames.ticks - len(frames.frames),
    )
    log.info(
        "exported %d frames of %s as %s to %s (%d ticks made no frame; topics not recorded: %s)",
        summary.frames,
        mcap,
        fmt,
        out,
        summary.dropped,
        ", ".join(summary.missing_topics) or "none",
    )
    return summary


# -- reading ---------------------------------------------------------------------------


class _Pairing:
    """Turns the record's messages, in recording order, into frames."""

    def __init__(self, observations: Sequence[str], actions: Sequence[str]) -> None:
        self.observation_topics = frozenset(observations)
        self.action_topics = frozenset(actions)
        self.observed: dict[str, Any] = {}
        self.commanded: dict[str, Any] = {}
        self.pending: tuple[int, int, int, dict[str, Any]] | None = None  # episode, tick, time
        self.episode = 0
        self.ticks = 0
        self.frames: list[Frame] = []
        self.task = ""

    def take(self, topic: str, time_ns: int, message: Any) -> None:
        if topic in self.observation_topics:
            self.observed[topic] = message
        if topic in self.action_topics:
            self.commanded[topic] = message
        if topic == EPISODE:
            self._tick(time_ns, message)

    def _tick(self, time_ns: int, message: Any) -> None:
        tick = int(message.tick)
        self.task = self.task or str(message.task)
        pending = self.pending
        if pending is not None and tick == pending[1]:
            self.ticks -= 1  # the same tick published again: its latest state counts
        elif pending is not None and tick == pending[1] + 1:
            episode, then, then_ns, observed = pending
            actions = dict(self.commanded)
            self.frames.append(Frame(episode, then, then_ns, observed, actions, message, time_ns))
        elif pending is not None:  # the tick went back: a new episode, a new task
            self.episode += 1
            self.commanded.clear()  # its observations of tick 0 came already: they stay
        self.ticks += 1
        self.pending = (self.episode, tick, time_ns, dict(self.observed))


def read_frames(path: Path, observations: Sequence[str], actions: Sequence[str]) -> Frames:
    """The frames of the MCAP record at ``path`` (see the module's docstring)."""
    if not path.is_file():
        raise ExportError(f"no MCAP file at {path}")
    pairing = _Pairing(observations, actions)
    wanted = pairing.observation_topics | pairing.action_topics | {EPISODE}
    recorded: set[str] = set()
    decoders: dict[int, Callable[[bytes], Any] | None] = {}
    ignored: set[int] = set()  # channels of the wrong side for their topic
    factory = DecoderFactory()
    try:
        with path.open("rb") as stream:
            reader = NonSeekingReader(stream)
            for schema, channel, message in reader.iter_messages(log_time_order=False):
                if channel.id in ignored:
                    continue
                if channel.id not in decoders:
                    if _wrong_side(channel.topic, channel.metadata.get(SIDE_KEY), pairing):
                        ignored.add(channel.id)
                        continue
                    decoders[channel.id] = (
                        factory.decoder_for(channel.message_encoding, schema)
                        if channel.topic in wanted
                        else None
                    )
                recorded.add(channel.topic)
                if channel.topic not in wanted:
                    continue
                decode = decoders[channel.id]
                if decode is None:
                    raise ExportError(f"{path}: {channel.topic} is not CDR with a ros2msg schema")
                pairing.take(channel.topic, message.log_time, decode(message.data))
    except _UNREADABLE as err:
        reason = f"{type(err).__name__}: {err}" if str(err) else type(err).__name__
        raise ExportError(f"{path} is not a complete, readable MCAP file ({reason})") from None
    present_obs = [t for t in dict.fromkeys(observations) if t in recorded]
    present_act = [t for t in dict.fromkeys(actions) if t in recorded]
    missing = [t for t in dict.fromkeys([*observations, *actions]) if t not in recorded]
    what = ", ".join(sorted(recorded - {EPISODE})) or "nothing"
    if not present_obs:
        raise ExportError(
            f"{path} has none of the observation topics {', '.join(observations)}; "
            f"it records {what}"
        )
    if not present_act:
        raise ExportError(
            f"{path} has none of the action topics {', '.join(actions)} (the controller "
            f"published no command there); it records {what}"
        )
    if EPISODE not in recorded:
        raise ExportError(f"{path} has no {EPISODE} messages, so its control ticks are unknown")
    frames = [
        f
        for f in pairing.frames
        if all(t in f.observations for t in present_obs)
        and all(t in f.actions for t in present_act)
    ]
    if not frames:
        raise ExportError(
            f"{path} has no frame: none of its {pairing.ticks} control ticks was followed by a "
            f"step with a message known on every topic of {', '.join([*present_obs, *present_act])}"
        )
    return Frames(frames, present_obs, present_act, missing, pairing.ticks, pairing.task)


def _wrong_side(topic: str, side: str | None, pairing: _Pairing) -> bool:
    """Whether a channel's side rules it out for its topic's role (None: not recorded)."""
    if side == "client":
        return topic in pairing.observation_topics or topic == EPISODE
    if side == "lab":
        return topic in pairing.action_topics
    return False


# -- flattening --------------------------------------------------------------------------


def _is_message(value: Any) -> bool:
    return hasattr(value, "__slots__") and hasattr(value, "_type")


def leaves(
    values: Sequence[Any], steps: tuple[str | int, ...] = (), stamp: bool = False
) -> list[Leaf]:
    """The fields of ``values`` (one field's values across a record), flattened."""
    first = values[0]
    if _is_message(first) and all(type(v) is type(first) for v in values):
        stamp = stamp or first._type in TIME_TYPES
        out: list[Leaf] = []
        for name in first.__slots__:
            out += leaves([getattr(v, name) for v in values], (*steps, name), stamp)
        return out
    if all(isinstance(v, bool) for v in values):
        return [Leaf(steps, "bool", stamp)]
    if all(isinstance(v, int) and not isinstance(v, bool) for v in values):
        return [Leaf(steps, "int", stamp)]
    if all(isinstance(v, int | float) and not isinstance(v, bool) for v in values):
        return [Leaf(steps, "float", stamp)]
    if all(isinstance(v, str) for v in values):
        return [Leaf(steps, "string", stamp)]
    if all(isinstance(v, bytes | bytearray) for v in values):
        return [Leaf(steps, "bytes", stamp)]
    if all(isinstance(v, list | tuple) for v in values):
        length = len(first)
        if length <= MAX_FLATTENED and all(len(v) == length for v in values):
            out = []
            for i in range(length):
                out += leaves([v[i] for v in values], (*steps, i), stamp)
            return out
    return [Leaf(steps, "json", stamp)]


def messages_of(frames: Sequence[Frame], topic: str, action: bool) -> list[Any]:
    """The message of ``topic`` in each frame (an action topic's if ``action``)."""
    return [f.actions[topic] if action else f.observations[topic] for f in frames]


def topic_leaves(frames: Sequence[Frame], topic: str, action: bool) -> list[Leaf]:
    """The flattened fields of ``topic`` over ``frames``, each distinct message once."""
    messages = messages_of(frames, topic, action)
    return leaves(list({id(m): m for m in messages}.values()))


def plain(value: Any) -> Any:
    """A decoded value as JSON: messages as objects, bytes as base64 text."""
    if _is_message(value):
        return {name: plain(getattr(value, name)) for name in value.__slots__}
    if isinstance(value, list | tuple):
        return [plain(v) for v in value]
    if isinstance(value, bytes | bytearray):
        return base64.b64encode(value).decode()
    return value


def _column(leaf: Leaf, messages: Sequence[Any]) -> pa.Array:
    values = [leaf.get(m) for m in messages]
    if leaf.kind == "bool":
        return pa.array(values, pa.bool_())
    if leaf.kind == "int":
        wide = any(v >= 2**63 for v in values)
        return pa.array(values, pa.uint64() if wide else pa.int64())
    if leaf.kind == "float":
        return pa.array(values, pa.float64())
    if leaf.kind == "string":
        return pa.array(values, pa.string())
    if leaf.kind == "bytes":
        return pa.array([bytes(v) for v in values], pa.binary())
    return pa.array([json.dumps(plain(v), ensure_ascii=False) for v in values], pa.string())


# -- parquet -----------------------------------------------------------------------------


def _write_parquet(
    frames: Frames, folder: Path, provenance: str
) -> tuple[list[Path], list[str], list[str]]:
    rows = frames.frames
    columns: dict[str, pa.Array] = {
        "episode_index": pa.array([f.episode for f in rows], pa.int64()),
        "frame_index": pa.array(_frame_indices(rows), pa.int64()),
        "tick": pa.array([f.tick for f in rows], pa.int64()),
        "timestamp": pa.array([f.time_ns / 1e9 for f in rows], pa.float64()),
        "next.reward": pa.array([float(f.next.reward) for f in rows], pa.float64()),
        "next.done": pa.array([f.next.status != "running" for f in rows], pa.bool_()),
        "next.success": pa.array([bool(f.next.success) for f in rows], pa.bool_()),
    }
    names: dict[str, list[str]] = {"observation": [], "action": []}
    for part, topics in (
        ("observation", frames.observation_topics),
        ("action", frames.action_topics),
    ):
        action = part == "action"
        for topic in topics:
            messages = messages_of(rows, topic, action)
            for leaf in topic_leaves(rows, topic, action):
                name = f"{part}.{topic}.{leaf.name}"
                columns[name] = _column(leaf, messages)
                names[part].append(name)
    table = pa.table(columns)
    described = {
        "observations": frames.observation_topics,
        "actions": frames.action_topics,
        "missing": frames.missing_topics,
        "task": frames.task,
    }
    table = table.replace_schema_metadata(
        {PROVENANCE_KEY: provenance, "labd.topics": json.dumps(described)}
    )
    path = folder / PARQUET_NAME
    pq.write_table(table, path, compression="zstd")
    return [path], names["observation"], names["action"]


def _frame_indices(rows: Sequence[Frame]) -> list[int]:
    indices: list[int] = []
    for i, frame in enumerate(rows):
        same = i > 0 and rows[i - 1].episode == frame.episode
        indices.append(indices[-1] + 1 if same else 0)
    return indices


# -- lerobot -----------------------------------------------------------------------------


def _vector(frames: Frames, topics: Sequence[str], action: bool) -> tuple[np.ndarray, list[str]]:
    """The fixed-length numeric fields of ``topics``, one float32 row per frame."""
    rows = frames.frames
    parts: list[np.ndarray] = []
    names: list[str] = []
    for topic in topics:
        messages = messages_of(rows, topic, action)
        for leaf in topic_leaves(rows, topic, action):
            if leaf.numeric and not leaf.stamp:
                parts.append(np.array([float(leaf.get(m)) for m in messages], np.float64))
                names.append(f"{topic}.{leaf.name}")
    if not parts:
        kind = "action" if action else "observation"
        raise ExportError(
            f"the {kind} topics {', '.join(topics)} have no fixed-length numeric field "
            "for LeRobot's vectors"
        )
    return np.stack(parts, axis=1).astype(np.float32), names


def _fps(frames: Frames) -> int:
    steps = {f.next_time_ns - f.time_ns for f in frames.frames}
    if len(steps) != 1 or min(steps) <= 0:
        raise ExportError("LeRobot needs evenly spaced frames; this record's ticks are not")
    fps = 1e9 / steps.pop()
    if not math.isclose(fps, round(fps), abs_tol=1e-6):
        raise ExportError(f"LeRobot needs a whole number of frames per second, not {fps:g}")
    return round(fps)


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


def _write_lerobot(
    frames: Frames, folder: Path, provenance: dict[str, Any]
) -> tuple[list[Path], list[str], list[str]]:
    rows = frames.frames
    fps = _fps(frames)
    state, state_names = _vector(frames, frames.observation_topics, action=False)
    action, action_names = _vector(frames, frames.action_topics, action=True)
    _, inverse = np.unique([f.episode for f in rows], return_inverse=True)
    episodes: list[int] = inverse.tolist()  # 0, 1, ... without gaps
    first_ns: dict[int, int] = {}
    for frame, episode in zip(rows, episodes, strict=True):
        first_ns.setdefault(episode, frame.time_ns)
    seconds = [(f.time_ns - first_ns[e]) / 1e9 for f, e in zip(rows, episodes, strict=True)]
    data: dict[str, np.ndarray] = {
        "observation.state": state,
        "action": action,
        "next.reward": np.array([f.next.reward for f in rows], np.float32),
        "next.done": np.array([f.next.status != "running" for f in rows], np.bool_),
        "next.success": np.array([bool(f.next.success) for f in rows], np.bool_),
        "timestamp": np.array(seconds, np.float32),
        "frame_index": np.array(_frame_indices(rows), np.int64),
        "episode_index": np.array(episodes, np.int64),
        "index": np.arange(len(rows), dtype=np.int64),
        "task_index": np.zeros(len(rows), np.int64),
    }
    features: dict[str, dict[str, Any]] = {
        key: {"dtype": str(value.dtype), "shape": [1], "names": None} for key, value in data.items()
    }
    features["observation.state"].update(shape=[len(state_names)], names=state_names)
    features["action"].update(shape=[len(action_names)], names=action_names)
    meta = folder / "meta"
    paths = {
        "info": meta / "info.json",
        "stats": meta / "stats.json",
        "tasks": meta / "tasks.parquet",
        "episodes": meta / "episodes" / "chunk-000" / "file-000.parquet",
        "data": folder / DATA_PATH.format(chunk_index=0, file_index=0),
    }
    for path in paths.values():
        path.parent.mkdir(parents=True, exist_ok=True)
    pq.write_table(pa.table({key: _arrow(value) for key, value in data.items()}), paths["data"])

    n_episodes = episodes[-1] + 1
    episode_rows: list[dict[str, Any]] = []
    for episode in range(n_episodes):
        where = np.flatnonzero(inverse == episode)
        row: dict[str, Any] = {
            "episode_index": episode,
            "tasks": [frames.task],
            "length": len(where),
            "data/chunk_index": 0,
            "data/file_index": 0,
            "dataset_from_index": int(where[0]),
            "dataset_to_index": int(where[-1]) + 1,
            "meta/episodes/chunk_index": 0,
            "meta/episodes/file_index": 0,
        }
        for feature, values in data.items():
            for stat, value in _stats(values[where]).items():
                row[f"stats/{feature}/{stat}"] = value
        episode_rows.append(row)
    pq.write_table(pa.Table.from_pylist(episode_rows), paths["episodes"])
    pq.write_table(_tasks_table([frames.task]), paths["tasks"])
    paths["stats"].write_text(json.dumps({k: _stats(v) for k, v in data.items()}, indent=2))
    info = {
        "codebase_version": LEROBOT_VERSION,
        "robot_type": None,
        "fps": fps,
        "total_episodes": n_episodes,
        "total_frames": len(rows),
        "total_tasks": 1,
        "chunks_size": CHUNKS_SIZE,
        "data_files_size_in_mb": DATA_FILE_MB,
        "video_files_size_in_mb": VIDEO_FILE_MB,
        "data_path": DATA_PATH,
        "video_path": None,
        "splits": {"train": f"0:{n_episodes}"},
        "features": features,
        "labd": {
            "provenance": provenance,
            "observation_topics": frames.observation_topics,
            "action_topics": frames.action_topics,
            "missing_topics": frames.missing_topics,
        },
    }
    paths["info"].write_text(json.dumps(info, indent=2, ensure_ascii=False))
    return list(paths.values()), state_names, action_names


def _arrow(values: np.ndarray) -> pa.Array:
    """A column as LeRobot's ``datasets`` writes it: vectors as fixed-size lists."""
    if values.ndim == 2:
        return pa.FixedSizeListArray.from_arrays(pa.array(values.reshape(-1)), values.shape[1])
    return pa.array(values)


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
