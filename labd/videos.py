"""Videos of filed records: rendered by the service when asked, or when the CPU is idle.

A trial's video is its task's first camera, rendered at 10 frames a second while its
record is replayed. Rendering costs about 10 ms a frame on a CPU rasteriser, three
quarters of what an evaluation's episode cost when workers rendered every record's
video before claiming their next trial; so workers only verify (``scheduler.worker``)
and the service renders:

- **when asked**: ``GET /api/trials/{id}/video`` (the trial page's player) renders the
  video if it is not made yet, at normal priority, and answers when it is (or 503 after
  ``ASK_WAIT`` seconds: the rendering goes on, ask again);
- **in the background** (``labd serve --videos background``, the default): while the
  lab runs no trial and has none queued, the newest replayed record without a video,
  one at a time, in a helper process of the idle scheduling class (``SCHED_IDLE``:
  it runs only on a core that nothing else wants, and gives it up at once). A lockstep
  tick is a millisecond or two of two processes waking each other, so even a process
  at nice 19 beside it slowed trials by a third; an idle lab costs nothing.

A video that cannot be made (a record with no camera, or that cannot be replayed here)
is remembered with the reason until the service restarts; asking for it again gives the
reason, without rendering again.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path

from labd.errors import LabError
from labd.trial import LabHost
from repository.blobs import BlobStore
from repository.index import Derived, Index
from repository.well_known import RECORD_FILE, VIDEO

log = logging.getLogger("labd.videos")
ASK_WAIT = 120.0  # seconds a request waits for its video to be rendered
ASKED_AT_ONCE = 2  # asked-for videos rendered at once
MODES = ("background", "asked")


class VideoUnavailable(LabError):
    """No video can be made of this trial; the message says why."""


class Videos:
    """Renders filed records' videos and files them beside the records."""

    def __init__(
        self,
        index: Index,
        store: BlobStore,
        host: LabHost,
        work: Path,
        *,
        background: bool = True,
        busy: Callable[[], bool] = lambda: False,
        poll: float = 5.0,
        seconds: float = 1800.0,
    ) -> None:
        self.index = index
        self.store = store
        self.host = host
        self.work = work
        self.background = background
        self.busy = busy  # whether trials are running or waiting: no background work then
        self.poll = poll
        self.seconds = seconds  # a render's limit
        self._rendering: dict[int, asyncio.Task[Derived]] = {}
        self._failed: dict[int, str] = {}
        self._asked = asyncio.Semaphore(ASKED_AT_ONCE)

    async def ask(self, trial_id: int, wait: float = ASK_WAIT) -> Derived:
        """The trial's video, rendered first if need be. ``VideoUnavailable`` with the
        reason if none can be made; ``TimeoutError`` if it is not made within ``wait``
        seconds (the rendering goes on)."""
        made = (await asyncio.to_thread(self.index.derived, trial_id)).get(VIDEO)
        if made is not None:
            return made
        if trial_id in self._failed:
            raise VideoUnavailable(self._failed[trial_id])
        task = self._rendering.get(trial_id)
        if task is None:
            task = self._start(trial_id, asked=True)
        async with asyncio.timeout(wait):
            return await asyncio.shield(task)

    async def run(self, stop: asyncio.Event) -> None:
        """Render videos in the background until ``stop`` is set (if ``background``)."""
        if not self.background:
            return
        while not stop.is_set():
            try:
                trial_id = await asyncio.to_thread(self._next)
            except Exception:  # the database away for a moment: try again later
                log.exception("could not look for records to render")
                trial_id = None
            if trial_id is None:
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(stop.wait(), self.poll)
                continue
            try:
                await self._start(trial_id, asked=False)
            except VideoUnavailable:
                pass  # remembered, with its reason
            except Exception:  # a bug: never let one record stop the rendering
                log.exception("trial %d: its video could not be rendered", trial_id)
                self._failed[trial_id] = "its video could not be rendered (the lab failed)"

    def _next(self) -> int | None:
        """The next record to render in the background, if the lab is idle."""
        if self.busy():
            return None
        return self.index.unrendered(VIDEO, {*self._failed, *self._rendering})

    async def close(self) -> None:
        """Stop rendering: what is being rendered is not filed."""
        tasks = list(self._rendering.values())
        for task in tasks:
            task.cancel()
        for task in tasks:
            with contextlib.suppress(asyncio.CancelledError, VideoUnavailable):
                await task

    def _start(self, trial_id: int, *, asked: bool) -> asyncio.Task[Derived]:
        task = asyncio.create_task(self._render(trial_id, asked=asked), name=f"video {trial_id}")
        self._rendering[trial_id] = task
        task.add_done_callback(lambda _: self._rendering.pop(trial_id, None))
        # a failure is kept in ``_failed`` and raised to whoever awaits; not logged twice
        task.add_done_callback(lambda t: t.cancelled() or t.exception())
        return task

    async def _render(self, trial_id: int, *, asked: bool) -> Derived:
        try:
            if asked:
                async with self._asked:
                    return await self._make(trial_id, background=False)
            return await self._make(trial_id, background=True)
        except VideoUnavailable as err:
            self._failed[trial_id] = str(err)
            raise
        except (TimeoutError, LabError, OSError) as err:
            reason = f"its video could not be rendered: {err}"
            log.error("trial %d: %s", trial_id, reason)
            self._failed[trial_id] = reason
            raise VideoUnavailable(reason) from None

    async def _make(self, trial_id: int, *, background: bool) -> Derived:
        trial = await asyncio.to_thread(self.index.trial, trial_id)
        if trial.mcap is None:
            raise VideoUnavailable(f"trial {trial_id} has no record to render")
        self.work.mkdir(parents=True, exist_ok=True)
        folder = Path(tempfile.mkdtemp(prefix=f"video-{trial_id}-", dir=self.work))
        try:
            mcap = await asyncio.to_thread(self.store.copy_to, trial.mcap, folder / RECORD_FILE)
            made = await asyncio.to_thread(
                self.host.video, mcap, folder, seconds=self.seconds, background=background
            )
            if made is None:
                raise VideoUnavailable(
                    f"trial {trial_id}'s record has no camera to render, or cannot be"
                    " replayed here (its replay verdict says why)"
                )
            size = made.stat().st_size
            digest = await asyncio.to_thread(self.store.put_file, made)
            item = Derived(VIDEO, digest, size, "video/mp4")
            await asyncio.to_thread(self.index.put_derived, trial_id, item)
            log.info("trial %d: its video is rendered (%d bytes)", trial_id, size)
            return item
        finally:
            await asyncio.to_thread(shutil.rmtree, folder, True)
