"""One time unit for the tests, as websockets' ``tests/utils.py`` has it.

A test waits for events (a message, a status, a file), never for time to pass; what
it still gives is how long it is willing to wait before it calls the event missing.
Those timeouts are multiples of ``MS``, which ``LABD_TESTS_TIMEOUT_FACTOR`` scales on a
machine that is slow or busy (a lab running Docker trials beside the tests): a timeout
only ever ends a test that would fail anyway, so a larger factor costs nothing on a
run that passes. How fast the lab is goes to ``bench/``, printed as ratios.

``eventually`` is the waiting itself, for asyncio tests: it polls a condition on the
test's own loop until it holds (``tests.faults.conftest.wait_for`` is the same for
threads).
"""

from __future__ import annotations

import asyncio
import os
import time
from collections.abc import Callable
from typing import TypeVar

T = TypeVar("T")

MS = 0.001 * float(os.environ.get("LABD_TESTS_TIMEOUT_FACTOR", "1"))
SECOND = 1000 * MS


async def eventually(
    what: str,
    condition: Callable[[], T],
    timeout: float = 30 * SECOND,
    *,
    detail: Callable[[], object] | None = None,
) -> T:
    """``condition()`` once it is true, checked every 10 ms on this loop; an
    ``AssertionError`` naming ``what`` (and ``detail()``) past ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    while not (value := condition()):
        if time.monotonic() > deadline:
            more = f": {detail()}" if detail else ""
            raise AssertionError(f"{what}: not within {timeout:g} s{more}")
        await asyncio.sleep(0.01)  # a poll of the condition, not a wait for time
    return value
