"""A compact summary of a record, for its page: plots, camera frames, a map, a 3D scene.

A trial's page must not download its MCAP to draw a plot, so the lab reads the record
once, when the trial is filed, and keeps this summary beside it (a derived artifact,
which never changes the record's digests). ``summarize`` reads the record;
``encode`` makes the stored form, gzip-compressed JSON; ``summary_blob`` does both
within a size budget (a small fraction of the record's size). The JSON::

    {"version": 1, "task": "icreate-maze", "ticks": 3001, "duration": 300.0,
     "t":    [0, 0.7, ...],          # seconds: the time of each point (N of them)
     "tick": [0, 7, ...],            # the control tick of each point
     "plots": [{"topic": "/odom", "side": "lab", "group": "pose",
                "labels": ["position.x", ...], "values": [[...N], ...]}, ...],
     "constant": [["/cmd_vel", "linear", "y", 0.0], ...],   # series that never changed
     "episode": {"status": "succeeded", "reason": "...", "ends": [[t, status], ...]},
     "camera": {"topic": ..., "t": [...], "width": 160, "height": 120, "columns": 16,
                "source": [320, 240], "sprite": "data:image/jpeg;base64,..."} | null,
     "map": {"frame": "odom", "walls": [[x0, y0, x1, y1]], "tags": [[id, x, y, nx, ny]],
             "goal": [x0, y0, x1, y1], "path": {"t": [...], "x": [...], "y": [...]}} | null,
     "scene": {"bodies": [...], "geoms": [...], "textures": [...],
               "qpos0": [...nq], "moving": [k, ...],   # the joint positions at the
               "qpos": [[...] per point]} | null,     # start; those that move, per point
     "ux": {"counts": {"key": 12, ...},       # a live page's user-experience events
            "events": [[t, kind, key, value], ...]} | null}   # (/ux/events), the first 300

Points are the record's control ticks (each ``/lab/episode`` message closes one),
decimated to at most ``MAX_POINTS`` (``series``). Observations (what the lab
published) are taken at their tick; commands (what a client published) are placed at
the tick the client saw when it sent them, held until replaced, as the robot holds
them. Camera frames, when the record has them, are thumbnails in one JPEG (a sprite,
``columns`` across, in time order). The map and the scene come from the task's model,
which the record carries (``scene``).
"""

from __future__ import annotations

import base64
import gzip
import io
import math
import time
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import orjson
from mcap.exceptions import McapError
from PIL import Image, UnidentifiedImageError

from labd.errors import SummaryError
from labd.graph.graph import Side
from labd.graph.types import TypeRegistry
from labd.recorder import scene, series
from labd.recorder.bag import mcap_path
from labd.recorder.reader import RecordedMessage, read_channels, read_messages
from labd.recorder.record import read_manifest
from repository.errors import ManifestError
from repository.manifest import Manifest
from repository.mcapfile import seeking
from repository.trial import EpisodeStatus
from repository.units import KiB
from repository.well_known import CLOCK, EPISODE, ROSOUT, UX_EVENTS

VERSION = 2
MAX_POINTS = 400  # per series: enough for a plot a page wide
MAX_UX = 300  # user-experience events listed (all are counted)
MIN_POINTS = 50  # the budget never cuts a series below this
MAX_FRAMES = 240  # camera thumbnails
MIN_FRAMES = 24  # the budget keeps at least this many (if the record has them)
THUMB_WIDTH = 160  # pixels; the height keeps the camera's aspect
SPRITE_COLUMNS = 16
QUALITY = 70  # JPEG quality of the thumbnails
BUDGET_SHARE = 12  # the stored summary stays under 1/12 of the record's MCAP ...
MIN_BUDGET = 16 * KiB  # ... or this, for short records
STILL = 1e-3  # m or rad: a joint that moves less is drawn where it started
PATH_STEP = 0.02  # metres between kept points of the robot's path
CAMERA = "/camera/image/compressed"
SKIPPED_TOPICS = frozenset({CLOCK, "/tf_static", "/camera/camera_info", ROSOUT})
IMAGE_TYPES = frozenset({"sensor_msgs/msg/CompressedImage", "sensor_msgs/msg/Image"})
ENDED = frozenset(status.value for status in EpisodeStatus if status.ended)  # as recorded
_UNREADABLE = (McapError, OSError, ValueError, EOFError, IndexError, KeyError)


@dataclass
class Reading:
    """Everything one pass over a record gathers, before decimation."""

    task: str = ""
    times: list[float] = field(default_factory=list)  # per tick, seconds
    ticks: list[int] = field(default_factory=list)
    status: str = ""
    reason: str = ""
    ends: list[list[Any]] = field(default_factory=list)
    lab: series.Columns = field(default_factory=series.Columns)
    client: series.Columns = field(default_factory=series.Columns)
    order: dict[tuple[str, str], Side] = field(default_factory=dict)  # (topic, group)
    frames: list[tuple[float, Image.Image]] = field(default_factory=list)
    source: tuple[int, int] | None = None
    model: Any = None
    poser: scene.Poser | None = None
    qpos: list[np.ndarray] = field(default_factory=list)
    root: str | None = None  # the frame /tf gives first from odom: the robot
    ux: list[list[Any]] = field(default_factory=list)  # [t, kind, key, value]
    ux_counts: dict[str, int] = field(default_factory=dict)


def summarize(
    path: str | Path,
    *,
    types: TypeRegistry | None = None,
    seconds: float | None = None,
    points: int = MAX_POINTS,
) -> dict[str, Any]:
    """The summary of the record at ``path`` (``SummaryError`` if it cannot be read, or
    reading takes longer than ``seconds``)."""
    return build(read(path, types=types, seconds=seconds), points)


def summary_blob(
    path: str | Path, *, types: TypeRegistry | None = None, seconds: float | None = None
) -> bytes:
    """The stored form of the record's summary (``encode``), cut to fit the budget:
    fewer points, then fewer frames, then smaller thumbnails, until it weighs at most
    1/``BUDGET_SHARE`` of the record (or ``MIN_BUDGET``)."""
    reading = read(path, types=types, seconds=seconds)
    budget = max(MIN_BUDGET, mcap_path(path).stat().st_size // BUDGET_SHARE)
    points, every, quality, width = MAX_POINTS, 1, QUALITY, THUMB_WIDTH
    while True:
        summary = build(reading, points, every=every, quality=quality, width=width)
        blob = encode(summary)
        if len(blob) <= budget:
            return blob
        frames = len(reading.frames) // every
        if points > MIN_POINTS:
            points = max(MIN_POINTS, points // 2)
        elif frames > MIN_FRAMES:
            every *= 2  # fewer frames of the same quality: a coarser strip, still sharp
        elif reading.frames and width > 64:
            width, quality = width * 3 // 4, max(40, quality - 10)
        else:
            return blob  # as small as it gets: the record is small, so is this


def encode(summary: dict[str, Any]) -> bytes:
    """Gzip-compressed JSON, the same bytes for the same summary."""
    return gzip.compress(orjson.dumps(summary), compresslevel=9, mtime=0)


def decode(blob: bytes) -> dict[str, Any]:
    value: dict[str, Any] = orjson.loads(gzip.decompress(blob))
    return value


# -- reading -----------------------------------------------------------------------------


def read(
    path: str | Path, *, types: TypeRegistry | None = None, seconds: float | None = None
) -> Reading:
    """One pass over the record: every tick's numbers, chosen frames, the robot's state."""
    deadline = None if seconds is None else time.monotonic() + seconds
    typestore = (types or TypeRegistry.shared()).typestore
    known = typestore.fielddefs
    reading = Reading()
    try:
        channels = read_channels(path)
        reading.task = _task(read_manifest(path))
        reading.model = scene.load(_attachments(path))
        if reading.model is not None:
            reading.poser = scene.Poser(reading.model)
        frames = sum(c.message_count for c in channels if c.topic == CAMERA)
        stride = max(1, math.ceil(frames / MAX_FRAMES))
        clock = _Clock()
        seen_frames = 0
        for count, message in enumerate(read_messages(path)):
            if deadline is not None and count % 512 == 0 and time.monotonic() > deadline:
                raise SummaryError(f"summarizing the record took longer than {seconds:g} s")
            if message.schema is None or message.topic in SKIPPED_TOPICS:
                continue
            if message.topic == CAMERA:
                if seen_frames % stride == 0:
                    _frame(reading, clock.seconds(message.log_time), message)
                seen_frames += 1
                continue
            if message.schema.name in IMAGE_TYPES or message.schema.name not in known:
                continue  # a repository's own types (the lab's registry lacks them)
            decoded = typestore.deserialize_cdr(message.data, message.schema.name)
            if message.topic == EPISODE:
                _tick(reading, clock, message, decoded)
            elif message.topic == UX_EVENTS:
                _ux(reading, clock.seconds(message.log_time), decoded)
            else:
                _observe(reading, message, decoded)
    except SummaryError:
        raise
    except _UNREADABLE as err:
        raise SummaryError(f"the record could not be read: {type(err).__name__}: {err}") from None
    return reading


class _Clock:
    """Seconds since the record began, never going back: a record of several episodes
    (a live session) restarts simulation time with each."""

    def __init__(self) -> None:
        self.start: int | None = None
        self.offset = 0.0
        self.last = 0.0

    def seconds(self, log_time: int, *, episode: bool = False) -> float:
        if self.start is None:
            self.start = log_time
        value = (log_time - self.start) / 1e9 + self.offset
        if episode and value < self.last:  # a new episode: carry on from the last one
            self.offset += self.last - value
            value = self.last
        if episode:
            self.last = value
        return value


def _task(held: dict[str, Any] | None) -> str:
    """The task the record's manifest names ("" when it holds none)."""
    if held is None:
        return ""
    try:
        return Manifest.from_json(held).task.name
    except ManifestError as err:
        raise SummaryError(f"the record's manifest cannot be read: {err}") from None


def _attachments(path: str | Path) -> dict[str, bytes]:
    with mcap_path(path).open("rb") as stream:
        return {a.name: a.data for a in seeking(stream).iter_attachments()}


def _tick(reading: Reading, clock: _Clock, message: RecordedMessage, episode: Any) -> None:
    """A ``/lab/episode``: the tick's observations are in; close it."""
    reading.lab.update(
        EPISODE, {("", "reward"): episode.reward, ("", "total_reward"): episode.total_reward}
    )
    reading.order.setdefault((EPISODE, ""), Side.LAB)
    t = clock.seconds(message.log_time, episode=True)
    reading.times.append(round(t, 3))
    reading.ticks.append(int(episode.tick))
    status = str(episode.status)
    if status in ENDED and reading.status not in ENDED:  # an episode ended at this tick
        reading.ends.append([round(t, 3), status])
    reading.status, reading.reason = status, str(episode.reason)
    reading.lab.snapshot()
    reading.client.snapshot()
    if reading.poser is not None:
        reading.qpos.append(reading.poser.qpos.copy())


def _ux(reading: Reading, t: float, event: Any) -> None:
    kind = str(event.kind)
    reading.ux_counts[kind] = reading.ux_counts.get(kind, 0) + 1
    if len(reading.ux) < MAX_UX:
        reading.ux.append([round(t, 3), kind, str(event.key), str(event.value)[:200]])


def _observe(reading: Reading, message: RecordedMessage, decoded: Any) -> None:
    side = message.side or Side.LAB
    values = series.flatten(decoded)
    (reading.client if side is Side.CLIENT else reading.lab).update(message.topic, values)
    for group, _ in values:
        reading.order.setdefault((message.topic, group), side)
    kind = getattr(decoded, "__msgtype__", "")
    if kind == "tf2_msgs/msg/TFMessage" and reading.root is None:
        reading.root = next(
            (str(t.child_frame_id) for t in decoded.transforms if t.header.frame_id == "odom"),
            None,
        )
    poser = reading.poser
    if poser is None or side is not Side.LAB:
        return
    if kind == "sensor_msgs/msg/JointState":
        poser.joint_states(decoded)
    elif kind == "tf2_msgs/msg/TFMessage":
        poser.tf(decoded)
    elif kind == "lab_msgs/msg/DetectedObjectArray":
        poser.objects(decoded)


def _frame(reading: Reading, t: float, message: RecordedMessage) -> None:
    data = bytes(_compressed_data(message))
    try:
        image = Image.open(io.BytesIO(data))
        reading.source = image.size
        image.draft("RGB", (THUMB_WIDTH, THUMB_WIDTH))  # JPEG: decode at a smaller scale
        reading.frames.append((round(t, 3), image.convert("RGB")))
    except (UnidentifiedImageError, OSError, ValueError):
        return  # a frame that does not decode is left out, as a viewer would skip it


def _compressed_data(message: RecordedMessage) -> memoryview:
    """The image bytes of a CDR ``sensor_msgs/msg/CompressedImage``, without decoding the
    whole message: header (stamp, frame_id), format, then ``data``."""
    buffer = memoryview(message.data)
    offset = 4 + 8  # encapsulation, stamp

    def string() -> None:
        nonlocal offset
        offset = (offset + 3) & ~3
        length = int.from_bytes(buffer[offset : offset + 4], "little")
        offset += 4 + length

    string()  # frame_id
    string()  # format
    offset = (offset + 3) & ~3
    length = int.from_bytes(buffer[offset : offset + 4], "little")
    return buffer[offset + 4 : offset + 4 + length]


# -- building ----------------------------------------------------------------------------


def build(
    reading: Reading,
    points: int,
    *,
    every: int = 1,
    quality: int = QUALITY,
    width: int = THUMB_WIDTH,
) -> dict[str, Any]:
    """The summary from a reading, with at most ``points`` points per series."""
    ticks = len(reading.times)
    starts = series.buckets(ticks, points) if ticks else np.zeros(0, dtype=np.int64)
    ends = np.append(starts[1:], ticks) - 1 if ticks else starts  # each bucket's last tick
    plots, constants = _plots(reading, starts)
    times = np.array(reading.times)
    return {
        "version": VERSION,
        "task": reading.task,
        "ticks": ticks,
        "duration": reading.times[-1] if reading.times else 0.0,
        "t": times[ends].tolist() if ticks else [],
        "tick": np.array(reading.ticks)[ends].tolist() if ticks else [],
        "plots": plots,
        "constant": constants,
        "episode": {"status": reading.status, "reason": reading.reason, "ends": reading.ends},
        "camera": _camera(reading.frames[::every], reading.source, quality, width),
        "map": _map(reading),
        "scene": _scene(reading, ends),
        "ux": {"counts": reading.ux_counts, "events": reading.ux} if reading.ux_counts else None,
    }


def _plots(reading: Reading, starts: np.ndarray) -> tuple[list[dict[str, Any]], list[list[Any]]]:
    columns = {**reading.lab.arrays(), **reading.client.arrays(shift=True)}
    grouped: dict[tuple[str, str], list[tuple[str, np.ndarray]]] = {}
    for (topic, (group, label)), column in columns.items():
        grouped.setdefault((topic, group), []).append((label, column))
    plots, constants = [], []
    ordered = sorted(
        reading.order.items(), key=lambda item: (item[0][0] != EPISODE, item[1] is Side.CLIENT)
    )
    for (topic, group), side in ordered:
        labels: list[str] = []
        values: list[list[float | None]] = []
        for label, column in grouped.get((topic, group), []):
            if not np.isfinite(column).any():
                continue  # never a number (a NaN a client sent, say): nothing to draw
            fixed = series.constant(column)
            if fixed is not None:
                constants.append([topic, group, label, fixed])
                continue
            labels.append(label)
            values.append(series.rounded(series.decimate(column, starts)))
        if labels:
            plots.append(
                {
                    "topic": topic,
                    "side": side.value,
                    "group": group,
                    "labels": labels,
                    "values": values,
                }
            )
    return plots, constants


def _camera(
    frames: list[tuple[float, Image.Image]],
    source: tuple[int, int] | None,
    quality: int,
    width: int,
) -> dict[str, Any] | None:
    if not frames or source is None:
        return None
    sw, sh = source
    height = max(1, round(width * sh / sw))
    columns = min(SPRITE_COLUMNS, len(frames))
    rows = math.ceil(len(frames) / columns)
    sprite = Image.new("RGB", (columns * width, rows * height))
    for k, (_, image) in enumerate(frames):
        thumb = image.resize((width, height), Image.Resampling.BILINEAR)
        sprite.paste(thumb, ((k % columns) * width, (k // columns) * height))
    out = io.BytesIO()
    sprite.save(out, format="JPEG", quality=quality, optimize=True)
    return {
        "topic": CAMERA,
        "t": [t for t, _ in frames],
        "width": width,
        "height": height,
        "columns": columns,
        "source": [sw, sh],
        "sprite": "data:image/jpeg;base64," + base64.b64encode(out.getvalue()).decode(),
    }


def _map(reading: Reading) -> dict[str, Any] | None:
    if reading.model is None:
        return None
    poser = reading.poser
    found = scene.floor_map(reading.model, poser.world_from_odom if poser else None)
    if found is None:
        return None
    xs = reading.lab.data.get(("/tf", (reading.root or "", "x")))
    ys = reading.lab.data.get(("/tf", (reading.root or "", "y")))
    found["path"] = _path(reading.times, xs or [], ys or [])
    return found


def _path(times: list[float], xs: Iterable[float], ys: Iterable[float]) -> dict[str, list[float]]:
    """The robot's way in ``odom``, a point each ``PATH_STEP`` metres (and the last)."""
    kept: dict[str, list[float]] = {"t": [], "x": [], "y": []}
    last: tuple[float, float] | None = None
    points = list(zip(times, xs, ys, strict=False))
    for k, (t, x, y) in enumerate(points):
        if not (math.isfinite(x) and math.isfinite(y)):
            continue
        if (
            last is None
            or math.hypot(x - last[0], y - last[1]) >= PATH_STEP
            or k == len(points) - 1
        ):
            kept["t"].append(t)
            kept["x"].append(round(x, 3))
            kept["y"].append(round(y, 3))
            last = (x, y)
    return kept


def _scene(reading: Reading, ends: np.ndarray) -> dict[str, Any] | None:
    """The model's description, and at each point the joint positions that moved."""
    if reading.model is None:
        return None
    described = scene.describe(reading.model)
    rest = np.asarray(reading.model.qpos0, dtype=np.float64)
    states = np.array(reading.qpos)[ends] if reading.qpos else np.zeros((0, len(rest)))
    # what moves less than STILL (settling, a detector's last digits) is drawn still
    moving = [k for k in range(len(rest)) if len(states) and np.ptp(states[:, k]) > STILL]
    start = states[0] if len(states) else rest
    described["qpos0"] = np.round(start, 4).tolist()
    described["moving"] = moving
    described["qpos"] = np.round(states[:, moving], 4).tolist()
    return described
