"""The worker files a record's page summary once the trial is filed; a summary that fails
or takes too long is logged and the trial stays filed without one."""

from __future__ import annotations

import time

from labd.errors import SummaryError
from labd.recorder.summary import decode
from labd.trial import LabHost
from repository.blobs import BlobStore
from repository.well_known import SUMMARY, SUMMARY_MEDIA_TYPE
from scheduler.worker import Worker, WorkerConfig
from tests.labd.test_recorder import record
from tests.scheduler.test_worker import claimed, queue, result  # noqa: F401  (fixtures)


class FailingHost(LabHost):
    def summarize(self, mcap, *, seconds):
        raise SummaryError("the record could not be read: it is damaged")


class SlowHost(LabHost):
    def summarize(self, mcap, *, seconds):
        time.sleep(seconds + 3)  # ignores its time, as a bug would
        return b""


def filed(queue, tmp_path, host, summary=120.0):  # noqa: F811
    """A worker with ``host``, and a trial of it filed with a real maze record."""
    store = BlobStore(str(tmp_path / "blobs"))
    config = WorkerConfig(
        name="w", work=tmp_path / "work", cache=tmp_path / "cache", summary=summary
    )
    worker = Worker(queue, store, backend=None, host=host, config=config)
    run = record(worker.host.types, tmp_path / "trial", "icreate-maze", ticks=5)
    claim = claimed(queue)
    filing = worker._filing(claim, result(run), None, run.summary.folder)
    assert queue.finish(claim.id, "w", filing)
    return worker, store, claim.id, run.summary.path


async def test_a_filed_trial_gets_its_summary_beside_its_record(queue, tmp_path):  # noqa: F811
    worker, store, trial_id, mcap = filed(queue, tmp_path, LabHost())
    await worker._summarize(trial_id, mcap)
    item = queue.index.derived(trial_id)[SUMMARY]
    assert item.media_type == SUMMARY_MEDIA_TYPE
    summary = decode(store.read_bytes(item.digest))
    assert summary["ticks"] == 6 and summary["plots"]  # (no model attached: no map)


async def test_a_summary_that_fails_is_logged_and_the_trial_stays_filed(queue, tmp_path, caplog):  # noqa: F811
    worker, _, trial_id, mcap = filed(queue, tmp_path, FailingHost())
    await worker._summarize(trial_id, mcap)
    assert SUMMARY not in queue.index.derived(trial_id)
    assert queue.trial(trial_id).status.ended
    assert "its summary could not be filed" in caplog.text and "damaged" in caplog.text


async def test_a_summary_past_its_time_is_given_up(queue, tmp_path, caplog):  # noqa: F811
    worker, _, trial_id, mcap = filed(queue, tmp_path, SlowHost(), summary=0.2)
    started = time.monotonic()
    await worker._summarize(trial_id, mcap)
    assert time.monotonic() - started < 3
    assert SUMMARY not in queue.index.derived(trial_id)
    assert "its summary took longer than 0.2 s" in caplog.text
