"""A log that limits itself: the same message, repeated, is let through a few times a
second and then counted, not written.

An error that repeats in a tight loop would otherwise fill the disk: with its
descriptors used up, the event loop logs each refused ``accept()`` with a traceback
(measured under a slowloris attack: 16 MB of log in 12 s). ``RepeatLimit`` keys each
record by its logger, level and message template (not the formatted text, so one
message with changing arguments is one message), lets ``burst`` of them through at
once and ``rate`` a second after that, and adds to the next one let through how many
it held back.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass

RATE = 2.0  # records of one message let through per second, after the burst
BURST = 5
KEYS = 1024  # messages followed at once; the least recent is forgotten past this


@dataclass
class _Bucket:
    tokens: float
    at: float
    dropped: int = 0
    since: float = 0.0


class RepeatLimit(logging.Filter):
    """Lets each message through ``burst`` times at once, then ``rate`` times a second."""

    def __init__(
        self,
        rate: float = RATE,
        burst: int = BURST,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        super().__init__()
        self.rate = rate
        self.burst = burst
        self.clock = clock
        self._buckets: OrderedDict[tuple[str, int, str], _Bucket] = OrderedDict()
        self._lock = threading.Lock()  # handlers filter on the thread that logs

    def filter(self, record: logging.LogRecord) -> bool:
        with self._lock:
            return self._let_through(record)

    def _let_through(self, record: logging.LogRecord) -> bool:
        key = (record.name, record.levelno, str(record.msg))
        now = self.clock()
        bucket = self._buckets.get(key)
        if bucket is None:
            bucket = self._buckets[key] = _Bucket(tokens=float(self.burst), at=now)
            if len(self._buckets) > KEYS:
                self._buckets.popitem(last=False)
        else:
            self._buckets.move_to_end(key)
            bucket.tokens = min(self.burst, bucket.tokens + (now - bucket.at) * self.rate)
            bucket.at = now
        if bucket.tokens < 1.0:
            if bucket.dropped == 0:
                bucket.since = now
            bucket.dropped += 1
            return False
        bucket.tokens -= 1.0
        if bucket.dropped:
            record.msg = (
                f"{record.msg} [and {bucket.dropped} more like it in the last"
                f" {now - bucket.since:.1f} s, not logged]"
            )
            bucket.dropped = 0
        return True


def limit_repeats(logger: logging.Logger | None = None) -> RepeatLimit:
    """Put a ``RepeatLimit`` on the plain stream handlers of ``logger`` (the root
    logger's, by default: the command's log, however ``logging.basicConfig`` made it),
    so that every record written there passes it; the filter. Handlers of other kinds
    (a program's that calls the command in process, such as pytest's capture) are left
    as they are."""
    limit = RepeatLimit()
    for handler in (logger or logging.getLogger()).handlers:
        if type(handler) is logging.StreamHandler:
            handler.addFilter(limit)
    return limit
