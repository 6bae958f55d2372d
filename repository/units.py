"""The units the lab counts in: sizes in bytes, moments in seconds since 1970 (UTC).

Limits, chunks and budgets are written as multiples of ``KiB``, ``MiB`` and ``GiB`` rather than
``1024 * 1024`` or ``1 << 20`` spelled out, so that a size reads the way it is meant
and is defined once. The index stores moments as seconds (a float, the clock's own
unit); ``moment`` is how they become the timezone-aware datetimes the API, the calendar
feeds and the messages show.

``repository`` imports no other package of ours, so this is where ``scheduler`` and
``labd`` take these from too. ``sandbox``, which imports nothing of ours either, keeps
its own ``MiB`` (``sandbox.api``) for its limits; ``controllers``, which runs in the
sandbox, its own as well.
"""

from __future__ import annotations

import datetime as dt

KiB = 1 << 10  # bytes
MiB = 1 << 20  # bytes
GiB = 1 << 30  # bytes


def moment(seconds: float) -> dt.datetime:
    """The UTC moment ``seconds`` after 1970 (what the index stores), timezone-aware."""
    return dt.datetime.fromtimestamp(seconds, dt.UTC)
