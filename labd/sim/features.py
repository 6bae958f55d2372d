"""What every task's export layout is made of (each task declares its own: ``TaskSpec.layout``).

A layout names the entries of a task's observation and action vectors.

An export (``repository.export``) has one row per control tick, and every row of a task
has these entries in this order, whichever topics the controller used, so the data of
different controllers and of people's demonstrations merge. Each entry is computed
from the record's messages (decoded with their own schemas); a command entry whose
topic had no message yet is its **neutral** value, what the robot does before any
command (stands still; holds its start pose). Entries constant by construction (an
odometry's z, its covariances) are left out. docs/tasks.md lists them with units.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any

from repository.export import Camera, Entry, Messages

CAMERA = Camera("camera", "/camera/image/compressed")
VERSION = "1"


def yaw(q: Any) -> float:
    """The rotation about z of a quaternion message."""
    return math.atan2(2 * (q.w * q.z + q.x * q.y), 1 - 2 * (q.y * q.y + q.z * q.z))


def field(
    topic: str, get: Callable[[Any], float], name: str, unit: str, doc: str, *, neutral: float = 0.0
) -> Entry:
    """An entry that is a function of the newest message of one topic."""

    def extract(messages: Messages, _topic: str) -> float | None:
        return float(get(messages[topic]))

    return Entry(name, (topic,), extract, neutral, unit, doc)


def joint_value(part: str, joint: str) -> Callable[[Any], float]:
    """A function of a JointState message: ``part`` (position, velocity, effort) of ``joint``."""

    def get(message: Any) -> float:
        return float(getattr(message, part)[list(message.name).index(joint)])

    return get


def names(entries: Sequence[Entry]) -> list[str]:
    return [e.name for e in entries]
