"""What a worker makes of a filed record (its summary, its replay's verdict) is made
beside its next trial, in helper processes: the worker does not wait for it to claim."""

from __future__ import annotations

import asyncio
import contextlib
import json
import threading
import time

from labd.trial import LabHost
from repository.blobs import BlobStore
from repository.trial import Order
from repository.well_known import REPLAY, SUMMARY
from scheduler.worker import Worker, WorkerConfig, _stopped
from tests.labd.test_recorder import record
from tests.scheduler.test_worker import COMMIT, queue, result  # noqa: F401  (fixtures)

REPLAY_SECONDS = 2.0


class SlowReplay(LabHost):
    """Replays as the lab does, once ``release`` is set (or after a pause, without one);
    notes when each replay ended."""

    def __init__(self, release: threading.Event | None = None) -> None:
        super().__init__()
        self.ended: dict[str, float] = {}
        self.release = release

    def replay(self, mcap, out, *, seconds=None):
        if self.release is None:
            time.sleep(REPLAY_SECONDS)
        else:  # a worker that waited for this replay to claim would wait here 30 s
            self.release.wait(30)
        done = super().replay(mcap, out, seconds=seconds)
        self.ended[mcap.parent.name] = time.monotonic()
        return done


async def test_the_next_trial_runs_while_the_last_ones_replay_is_made(
    queue,  # noqa: F811
    registry,
    tmp_path,
    monkeypatch,
):
    started: dict[str, float] = {}

    async def run_trial(spec, *, out, **_):  # a recorded pointmass episode, as a trial's
        started[out.name] = time.monotonic()
        if len(started) == 2:
            host.release.set()  # the first trial's replay ends only once the second runs
        run = record(registry, out, "icreate-maze", seed=spec.seed, ticks=5, manifest=True)
        return result(run)

    monkeypatch.setattr("scheduler.worker.run_trial", run_trial)
    alice = queue.index.user("alice")
    order = Order(repository="/r", commit=COMMIT, task="icreate-maze", public=True)
    ids = [queue.submit(alice, order.episode(seed)) for seed in (4, 5)]
    host = SlowReplay(threading.Event())
    config = WorkerConfig(name="w", work=tmp_path / "work", cache=tmp_path / "cache", poll=0.1)
    worker = Worker(queue, BlobStore(str(tmp_path / "blobs")), None, host, config)
    stop = asyncio.Event()
    running = asyncio.create_task(worker.run(stop))
    try:
        async with asyncio.timeout(120):
            while not all(REPLAY in queue.index.derived(i) for i in ids):
                await asyncio.sleep(0.1)
    finally:
        stop.set()
        await running
    first, second = (f"trial-{i}-1" for i in ids)
    # the second trial was claimed and run before the first one's replay ended
    assert started[second] < host.ended[first]
    for trial_id in ids:
        made = queue.index.derived(trial_id)
        assert SUMMARY in made
        verdict = json.loads(worker.store.read_bytes(made[REPLAY].digest))
        assert verdict["verified"] is True, verdict["said"]
        assert verdict["video"] is None  # videos are the service's to render
    assert list(config.work.iterdir()) == []  # each folder removed once its record was used


async def test_a_stopped_worker_stops_what_it_was_making_of_its_last_record(
    queue,  # noqa: F811
    registry,
    tmp_path,
    monkeypatch,
):
    async def run_trial(spec, *, out, **_):
        return result(record(registry, out, "icreate-maze", seed=spec.seed, ticks=5, manifest=True))

    monkeypatch.setattr("scheduler.worker.run_trial", run_trial)
    alice = queue.index.user("alice")
    order = Order(repository="/r", commit=COMMIT, task="icreate-maze", seed=4, public=True)
    trial_id = queue.submit(alice, order)
    config = WorkerConfig(name="w", work=tmp_path / "work", cache=tmp_path / "cache", poll=0.1)
    worker = Worker(queue, BlobStore(str(tmp_path / "blobs")), None, SlowReplay(), config)
    stop = asyncio.Event()
    running = asyncio.create_task(worker.run(stop))
    async with asyncio.timeout(60):
        while not queue.index.trial(trial_id).status.ended:
            await asyncio.sleep(0.05)
    stop.set()
    async with asyncio.timeout(REPLAY_SECONDS + 30):
        await running  # its replay's thread ends on its own; the worker does not wait for it
    assert queue.index.trial(trial_id).status.ended
    assert REPLAY not in queue.index.derived(trial_id)


async def test_a_record_whose_making_was_cancelled_does_not_stop_the_worker(
    queue,  # noqa: F811
    tmp_path,
):
    """What is made of the last record ending badly (cancelled, or a bug) is its own
    business: the worker waiting for it goes on."""
    config = WorkerConfig(name="w", work=tmp_path / "work", cache=tmp_path / "cache")
    worker = Worker(queue, BlobStore(str(tmp_path / "blobs")), None, LabHost(), config)

    async def forever():
        await asyncio.Event().wait()

    async def broken():
        raise RuntimeError("a bug")

    for made in (forever, broken):
        worker._deriving = asyncio.create_task(made())
        await asyncio.sleep(0)
        if made is forever:
            worker._deriving.cancel()
        await asyncio.wait_for(worker.settled(), 5)  # returns; raises nothing
        if made is broken:
            assert isinstance(worker._deriving.exception(), RuntimeError)


async def test_a_task_that_loses_its_cancel_is_cancelled_again():
    """On Python 3.11 a ``wait_for`` whose call ends as its task is cancelled drops the
    cancel; a worker stopping its heartbeat must not wait for ever on one that did."""

    async def stubborn():
        with contextlib.suppress(asyncio.CancelledError):
            await asyncio.sleep(30)  # the first cancel, lost
        await asyncio.sleep(30)

    task = asyncio.create_task(stubborn())
    await asyncio.sleep(0)
    await asyncio.wait_for(_stopped(task), 10)
    assert task.cancelled()
