"""Fakes for unit tests of logic: manual clocks and a recording transport."""

from __future__ import annotations

import heapq
import itertools
import json
from collections.abc import Callable
from typing import Any

import cbor2
import orjson

from repository.index import Derived
from repository.well_known import REPLAY
from scheduler.queue import Queue


class WallClock:
    """Seconds since the epoch that move only when the test sets ``now``: the index's,
    the queue's and the reservations' clock in tests of leases, quotas and expiries."""

    def __init__(self, now: float) -> None:
        self.now = now

    def __call__(self) -> float:
        return self.now


class ManualTimers:
    """A monotonic clock that moves only when the test says so."""

    def __init__(self) -> None:
        self.now = 0.0
        self._heap: list[tuple[float, int, _Handle]] = []
        self._seq = itertools.count()

    def time(self) -> float:
        return self.now

    def call_later(self, delay: float, callback: Callable[..., Any], *args: Any) -> _Handle:
        handle = _Handle(callback, args)
        heapq.heappush(self._heap, (self.now + delay, next(self._seq), handle))
        return handle

    def advance(self, seconds: float) -> None:
        """Move time forward, running every timer that falls due, in order."""
        target = self.now + seconds
        while self._heap and self._heap[0][0] <= target:
            when, _, handle = heapq.heappop(self._heap)
            self.now = when
            if not handle.cancelled:
                handle.callback(*handle.args)
        self.now = target

    @property
    def pending(self) -> int:
        return sum(1 for _, _, h in self._heap if not h.cancelled)


class _Handle:
    def __init__(self, callback: Callable[..., Any], args: tuple[Any, ...]) -> None:
        self.callback = callback
        self.args = args
        self.cancelled = False

    def cancel(self) -> None:
        self.cancelled = True


class RecordingTransport:
    """Collects what a session asks of its connection."""

    def __init__(self) -> None:
        self.wakes = 0
        self.closed: tuple[int, str] | None = None
        self.keys: list[str] = []

    def wake(self) -> None:
        self.wakes += 1

    def close(self, code: int, reason: str) -> None:
        self.closed = (code, reason)

    def authorize(self, key: str) -> None:
        self.keys.append(key)


def drain(session: Any) -> list[Any]:
    """Every frame the session has queued, decoded (JSON text or CBOR binary)."""
    out = []
    while (frames := session.next_frames()) is not None:
        for frame in frames:
            out.append(orjson.loads(frame.data) if frame.text else cbor2.loads(frame.data))
    return out


def file_unchecked(service: Any, trial_id: int, worker: str, filing: Any) -> bool:
    """File ``filing`` of a trial ``worker`` holds as if the lab had held it to its record.

    For tests of what the lab serves of a made-up record (a few bytes, a made-up digest),
    not of filing: the one check of a filing (``scheduler.filing``) has tests of its own.
    The same index and keys, a queue without the check.
    """
    return Queue(service.index, service.config.queue, service.keyring).finish(
        trial_id, worker, filing
    )


def verify_episodes(service: Any, trial_ids: Any) -> None:
    """File a replay verdict that says "verified" beside each trial, as the lab's own
    replay would (its verdicts are blobs of its store), for tests of what the lab makes
    of verified records rather than of replaying."""
    verdict = json.dumps({"verified": True}).encode()
    digest = service.store.put_bytes(verdict)
    for trial_id in trial_ids:
        service.index.put_derived(
            trial_id, Derived(REPLAY, digest, len(verdict), "application/json")
        )
