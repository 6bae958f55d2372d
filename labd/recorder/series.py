"""A record's messages as time series: named numbers per tick, then decimated for a page.

``flatten`` turns one decoded message (a rosbags object) into numbers keyed by
``(group, label)``: a plot per group, a line per label. The group is the message's
top-level field (``pose`` and ``twist`` of an ``/odom``), or the message itself when
its fields are plain numbers (a ``/bumper``). Inside, fields are flattened by path
(``position.x``), with these conventions:

- quaternions become ``roll``, ``pitch`` and ``yaw`` (radians), which a person reads;
- a ``JointState``'s ``position``, ``velocity`` and ``effort`` are labelled by joint name;
- a ``TFMessage`` gives a group per child frame (``x``, ``y``, ``z``, ``roll``, ...);
- a ``JointTrajectory`` gives its last point's ``positions`` by joint name (``target``);
- other sequences of messages give their length (``tags count``);
- booleans are 0 and 1; strings, bytes, stamps and covariances are left out.

``Columns`` keeps every tick's latest value of every key (sample and hold, as the lab
holds commands), and ``decimate`` cuts them to a few hundred points per series: each
bucket of ticks keeps its value farthest from the bucket's mean, so a spike (a reward
bonus, a bump) survives decimation where plain subsampling would lose it.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np

Key = tuple[str, str]  # (group, label)

SKIPPED_TYPES = frozenset(
    {
        "std_msgs/msg/Header",
        "builtin_interfaces/msg/Time",
        "builtin_interfaces/msg/Duration",
    }
)
SKIPPED_FIELDS = frozenset({"covariance", "header"})
MAX_ARRAY = 8  # numeric arrays up to this long are plotted element by element
RESOLUTION = 1000  # a series is rounded to a 1/RESOLUTION of its range (below a pixel)


def flatten(message: Any) -> dict[Key, float]:
    """The numbers of one decoded message, keyed by (group, label)."""
    kind = getattr(message, "__msgtype__", "")
    out: dict[Key, float] = {}
    if kind == "sensor_msgs/msg/JointState":
        names = list(message.name)
        for part in ("position", "velocity", "effort"):
            values = getattr(message, part)
            for name, value in zip(names, values, strict=False):
                out[(part, name)] = float(value)
        return out
    if kind == "tf2_msgs/msg/TFMessage":
        for item in message.transforms:
            group = str(item.child_frame_id)
            t, q = item.transform.translation, item.transform.rotation
            out[(group, "x")], out[(group, "y")], out[(group, "z")] = t.x, t.y, t.z
            for label, value in zip(("roll", "pitch", "yaw"), euler(q), strict=True):
                out[(group, label)] = value
        return out
    if kind == "trajectory_msgs/msg/JointTrajectory":
        if message.points:
            last = message.points[-1].positions
            for name, value in zip(message.joint_names, last, strict=False):
                out[("target", str(name))] = float(value)
        return out
    for name, value in _fields(message):
        if name in SKIPPED_FIELDS:
            continue
        if _is_message(value):
            for label, number in _numbers(value, "", name):
                out[(name, label)] = number
        else:
            for label, number in _numbers(value, name):
                out[("", label)] = number
    return out


def euler(q: Any) -> tuple[float, float, float]:
    """Roll, pitch and yaw (radians, ZYX) of a quaternion with fields x, y, z, w."""
    x, y, z, w = float(q.x), float(q.y), float(q.z), float(q.w)
    roll = math.atan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = math.asin(max(-1.0, min(1.0, 2 * (w * y - z * x))))
    yaw = math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return roll, pitch, yaw


def _fields(message: Any) -> Iterator[tuple[str, Any]]:
    for name, spec in message.__dataclass_fields__.items():
        if name.startswith("_"):
            continue
        value = getattr(message, name)
        if isinstance(value, list) and "__msg__" in str(spec.type):
            value = _Sequence(value)  # of messages: its length, even when empty
        yield name, value


class _Sequence(list[Any]):
    """A field that is a sequence of messages (so its length is plotted)."""


def _is_message(value: Any) -> bool:
    return hasattr(value, "__msgtype__")


def _numbers(value: Any, path: str, under: str = "") -> Iterator[tuple[str, float]]:
    """The numbers inside one field's value, labelled by their path below the group.

    ``under`` is the name of the field that holds ``value``: a field of the same name
    inside it (``pose.pose``, ``twist.twist``) adds nothing to the label."""
    if _is_message(value):
        kind = value.__msgtype__
        if kind in SKIPPED_TYPES:
            return
        if kind == "geometry_msgs/msg/Quaternion":
            for label, number in zip(("roll", "pitch", "yaw"), euler(value), strict=True):
                yield _join(path, label), number
            return
        for name, inner in _fields(value):
            if name not in SKIPPED_FIELDS:
                yield from _numbers(inner, path if name == under else _join(path, name), name)
        return
    if isinstance(value, bool | int | float | np.bool_ | np.integer | np.floating):
        yield path, float(value)  # booleans as 0 and 1
    elif isinstance(value, np.ndarray):
        if value.dtype.kind in "iuf" and value.dtype != np.uint8 and 0 < len(value) <= MAX_ARRAY:
            for i, number in enumerate(value.tolist()):
                yield f"{path}[{i}]", float(number)
    elif isinstance(value, _Sequence):
        yield _join(path, "count"), float(len(value))


def _join(path: str, name: str) -> str:
    return f"{path}.{name}" if path else name


@dataclass
class Columns:
    """Every key's latest value at each tick: a column per key, NaN before its first."""

    ticks: int = 0
    data: dict[tuple[str, Key], list[float]] = field(default_factory=dict)
    latest: dict[tuple[str, Key], float] = field(default_factory=dict)

    def update(self, topic: str, values: dict[Key, float]) -> None:
        for key, value in values.items():
            self.latest[(topic, key)] = value

    def snapshot(self) -> None:
        """Close one tick: every key holds its latest value."""
        for key, value in self.latest.items():
            column = self.data.get(key)
            if column is None:
                column = self.data[key] = [math.nan] * self.ticks
            column.append(value)
        self.ticks += 1

    def arrays(self, *, shift: bool = False) -> dict[tuple[str, Key], np.ndarray]:
        """The columns as arrays. ``shift``: a tick's value is the one taken at the next
        snapshot (what a controller sent after seeing that tick), the last one at the end."""
        out = {}
        for key, column in self.data.items():
            values = np.array(column, dtype=np.float64)
            if shift and len(values):
                values = np.append(values[1:], self.latest[key])
            out[key] = values
        return out


def buckets(ticks: int, points: int) -> np.ndarray:
    """The start of each of ``min(ticks, points)`` buckets of ticks, as even as can be."""
    count = max(1, min(ticks, points))
    return np.unique(np.linspace(0, ticks, count + 1).astype(np.int64)[:-1])


def decimate(values: np.ndarray, starts: np.ndarray) -> np.ndarray:
    """One value per bucket (``starts``, from ``buckets``): the one farthest from the
    bucket's mean (NaN where the bucket holds none)."""
    if len(starts) == len(values):
        return values
    finite = np.isfinite(values)
    filled = np.where(finite, values, 0.0)
    counts = np.add.reduceat(finite.astype(np.int64), starts)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.add.reduceat(filled, starts) / counts
        high = np.fmax.reduceat(np.where(finite, values, -np.inf), starts)
        low = np.fmin.reduceat(np.where(finite, values, np.inf), starts)
        chosen = np.where(high - mean >= mean - low, high, low)
    result: np.ndarray = np.where(counts > 0, chosen, np.nan)
    return result


def constant(values: np.ndarray) -> float | None:
    """The value of a series that never changes (None if it does, or has none)."""
    finite = values[np.isfinite(values)]
    if len(finite) == 0:
        return None
    first = float(finite[0])
    return first if bool(np.all(finite == first)) else None


def rounded(values: np.ndarray) -> list[float | None]:
    """A series rounded to a ``RESOLUTION``-th of its range, NaN as None (JSON null)."""
    finite = values[np.isfinite(values)]
    span = float(finite.max() - finite.min()) if len(finite) else 0.0
    digits = 6 if span <= 0 else max(0, min(6, math.ceil(-math.log10(span / RESOLUTION))))
    out: list[float | None] = []
    for v in np.round(values, digits).tolist():
        out.append(None if not math.isfinite(v) else (int(v) if v.is_integer() else v))
    return out
