"""The API's export builds: one build per export however many ask, a few at a time,
and many-trial exports kept on disk within their budget."""

from __future__ import annotations

import asyncio
import os
import threading

import pytest

from labd.api.builds import Builds
from labd.api.errors import ApiError
from tests.helpers.timing import eventually


async def test_requests_for_one_export_share_its_build(tmp_path):
    """Four requests at once for one export: one build, and each gets what it made."""
    builds = Builds(tmp_path)
    calls = []
    release = threading.Event()

    def build() -> str:
        calls.append(1)
        release.wait(10)
        return "made"

    waiting = [asyncio.ensure_future(builds.once("k", build)) for _ in range(4)]
    await eventually("the build to start", lambda: calls)  # every request in (one step each)
    release.set()
    assert await asyncio.gather(*waiting) == ["made"] * 4
    assert len(calls) == 1 and builds.made == 1


async def test_a_failed_build_fails_its_waiters_and_is_tried_again(tmp_path):
    """A build's error is each waiting request's; the next request builds again."""
    builds = Builds(tmp_path)

    def broken() -> str:
        raise ValueError("no")

    results = await asyncio.gather(
        *(builds.once("k", broken) for _ in range(3)), return_exceptions=True
    )
    assert all(isinstance(r, ValueError) for r in results)
    assert await builds.once("k", lambda: "made") == "made"


async def test_past_the_waiting_limit_a_new_export_is_a_503(tmp_path):
    """With one build running and its waiting room full, another export is refused."""
    builds = Builds(tmp_path, builds=1, waiting=2)
    release = threading.Event()
    running = [
        asyncio.ensure_future(builds.once(f"k{n}", lambda: release.wait(10))) for n in range(3)
    ]
    await asyncio.sleep(0)
    with pytest.raises(ApiError) as refused:
        await builds.once("k3", lambda: True)
    assert refused.value.status == 503 and "retry" in str(refused.value)
    release.set()
    assert await asyncio.gather(*running) == [True] * 3


def test_kept_exports_stay_within_their_budget(tmp_path):
    """Past the budget the least recently used exports go; the one just kept stays."""
    builds = Builds(tmp_path / "exports", keep_bytes=250)
    for n in range(3):
        made = builds.scratch() / "x.zip"
        made.write_bytes(b"x" * 100)
        builds.keep(f"k{n}", made)
        os.utime(tmp_path / "exports" / f"k{n}.zip", (1000 + n, 1000 + n))
    assert builds.kept("k0") is None  # the oldest, dropped when k2 came
    assert builds.kept("k1") is not None and builds.kept("k2") is not None
