"""The worker's filing of a trial: blobs, verdicts of reruns, a store that fails."""

from __future__ import annotations

import errno

import pytest

from repository.blobs import BlobStore
from repository.index import Index
from scheduler.queue import Queue
from scheduler.runner import TrialResult
from scheduler.worker import Worker, WorkerConfig, manifest_changes
from tests.labd.test_recorder import record

COMMIT = "c" * 40


@pytest.fixture
def queue(tmp_path):
    index = Index.open(f"sqlite:///{tmp_path / 'index.sqlite'}")
    index.add_user("alice", max_running=5)
    yield Queue(index)
    index.close()


def worker(queue, store, tmp_path):
    config = WorkerConfig(name="w", work=tmp_path / "work", cache=tmp_path / "cache")
    return Worker(queue, store, backend=None, types=None, config=config)  # no trial is run


def claimed(queue, rerun_of=None):
    alice = queue.index.user("alice")
    queue.submit(
        alice,
        repository="/r",
        ref=None,
        commit=COMMIT,
        task="pointmass",
        params={},
        seed=4,
        public=True,
        rerun_of=rerun_of,
    )
    return queue.claim("w")


def result(run, status="succeeded"):
    out = run.summary.folder
    return TrialResult(
        status,
        "the episode ended",
        out,
        manifest={"versions": {"labd": "1"}},
        data_digest=run.summary.data_digest,
        digest_topics=sorted(run.topics),
    )


def file(queue, w, claim, res):
    values = w._record(claim, res, res.folder)
    assert queue.finish(claim.id, "w", **values)
    return queue.index.trial(claim.id)


def test_a_rerun_with_the_same_data_reproduced(queue, registry, tmp_path):
    store = BlobStore(str(tmp_path / "blobs"))
    w = worker(queue, store, tmp_path)
    original = file(queue, w, claimed(queue), result(record(registry, tmp_path / "a", seed=4)))
    assert store.exists(original["mcap"])
    again = claimed(queue, rerun_of=original["id"])
    row = file(queue, w, again, result(record(registry, tmp_path / "b", seed=4)))
    assert row["reproduced"] is True
    assert row["divergence"] is None


def test_a_rerun_that_diverged_says_where(queue, registry, tmp_path):
    """The verdict names the tick and topic of the first differing message."""
    store = BlobStore(str(tmp_path / "blobs"))
    w = worker(queue, store, tmp_path)
    original = file(queue, w, claimed(queue), result(record(registry, tmp_path / "a", seed=4)))
    changed = record(registry, tmp_path / "b", seed=4, change_at=6)
    again = claimed(queue, rerun_of=original["id"])
    res = result(changed)
    res.manifest = {"versions": {"labd": "2"}}
    row = file(queue, w, again, res)
    assert row["reproduced"] is False
    assert row["divergence"].startswith("diverged at tick 6 on /cmd_vel")
    assert row["divergence"].endswith("the manifest differs in versions.labd")


class FullDisk:
    def put_file(self, path):
        raise OSError(errno.ENOSPC, "No space left on device")

    def copy_to(self, digest, dest):
        raise AssertionError("not reached")


def test_a_store_that_fails_files_the_trial_as_failed(queue, registry, tmp_path):
    """A full disk while filing is a failed trial with the reason, not a lost one."""
    w = worker(queue, FullDisk(), tmp_path)
    claim = claimed(queue)
    row = file(queue, w, claim, result(record(registry, tmp_path / "a", seed=4)))
    assert row["status"] == "failed"
    assert "could not store" in row["reason"]
    assert "No space left" in row["reason"]


def test_manifest_changes_lists_dotted_keys():
    a = {"seed": 1, "versions": {"labd": "1", "mujoco": "3"}, "task": "x"}
    b = {"seed": 1, "versions": {"labd": "2", "mujoco": "3"}, "extra": True}
    assert manifest_changes(a, b) == ["extra", "task", "versions.labd"]
