"""The worker's filing of a trial: blobs, verdicts of reruns, a store that fails."""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import errno

import pytest

from labd.trial import LabHost
from repository.blobs import BlobStore
from repository.index import Index
from repository.manifest import Manifest
from repository.trial import Ending, Order, Outcome, Status
from sandbox.api import Limits
from scheduler.host import Episode
from scheduler.queue import Queue, QueueConfig
from scheduler.runner import RunOptions, TrialResult
from scheduler.worker import Worker, WorkerConfig, manifest_changes
from tests.helpers.githttp import GitRepo
from tests.helpers.manifests import trial_manifest
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
    return Worker(queue, store, backend=None, host=LabHost(), config=config)  # runs no trial


def claimed(queue, rerun_of=None):
    alice = queue.index.user("alice")
    order = Order(
        repository="/r", commit=COMMIT, task="pointmass", seed=4, public=True, rerun_of=rerun_of
    )
    queue.submit(alice, order)
    return queue.claim("w")


def ran(labd: str) -> Manifest:
    """A trial's manifest, made by labd version ``labd``."""
    made = trial_manifest("pointmass", "1", {}, 4, model_sha256="0" * 64, commit=COMMIT)
    return dataclasses.replace(made, versions=dataclasses.replace(made.versions, labd=labd))


def result(run):
    out = run.summary.folder
    return TrialResult(
        Ending.success("the episode ended"),
        out,
        manifest=ran("1"),
        data_digest=run.summary.data_digest,
        digest_topics=sorted(run.topics),
    )


def file(queue, w, claim, res):
    filing = w._filing(claim, res, None, res.folder)
    assert queue.finish(claim.id, "w", filing)
    return queue.index.trial(claim.id)


def test_a_rerun_with_the_same_data_reproduced(queue, registry, tmp_path):
    store = BlobStore(str(tmp_path / "blobs"))
    w = worker(queue, store, tmp_path)
    original = file(queue, w, claimed(queue), result(record(registry, tmp_path / "a", seed=4)))
    assert store.exists(original.mcap)
    again = claimed(queue, rerun_of=original.id)
    row = file(queue, w, again, result(record(registry, tmp_path / "b", seed=4)))
    assert row.reproduced is True
    assert row.divergence is None
    assert row.verdict == "reproduced"


def test_a_rerun_that_diverged_says_where(queue, registry, tmp_path):
    """The verdict names the tick and topic of the first differing message."""
    store = BlobStore(str(tmp_path / "blobs"))
    w = worker(queue, store, tmp_path)
    original = file(queue, w, claimed(queue), result(record(registry, tmp_path / "a", seed=4)))
    changed = record(registry, tmp_path / "b", seed=4, change_at=6)
    again = claimed(queue, rerun_of=original.id)
    res = result(changed)
    res.manifest = ran("2")
    row = file(queue, w, again, res)
    assert row.reproduced is False
    assert row.divergence.startswith("diverged at tick 6 on /cmd_vel")
    assert row.divergence.endswith("the manifest differs in versions.labd")


class FullDisk:
    def put_file(self, path):
        raise OSError(errno.ENOSPC, "No space left on device")

    def copy_to(self, digest, dest):
        raise AssertionError("not reached")


def test_a_store_that_fails_files_the_trial_as_an_error(queue, registry, tmp_path):
    """A full disk while filing is an error with the reason, not a lost trial."""
    w = worker(queue, FullDisk(), tmp_path)
    claim = claimed(queue)
    row = file(queue, w, claim, result(record(registry, tmp_path / "a", seed=4)))
    assert (row.status, row.outcome) == (Status.FINISHED, Outcome.ERROR)
    assert "could not store" in row.reason
    assert "No space left" in row.reason


def test_manifest_changes_lists_dotted_keys():
    a = {"seed": 1, "versions": {"labd": "1", "mujoco": "3"}, "task": "x"}
    b = {"seed": 1, "versions": {"labd": "2", "mujoco": "3"}, "extra": True}
    assert manifest_changes(a, b) == ["extra", "task", "versions.labd"]


# -- a trial always ends (faults inside the lab) --------------------------------------------

LAB_TOML = '[controller]\ncommand = ["python", "c.py"]\ntask = "icreate-maze"\n'


class BuggyHost(LabHost):
    """A lab side with a bug: checking the task raises what no one expects."""

    def check(self, task, params):
        raise RuntimeError("a bug in the lab")


class StuckLab:
    """A lab side that never starts (and, with ``hang_finish``, never stops either)."""

    digest_topics = ()

    def __init__(self, setup, hang_finish=False):
        self.hang_finish = hang_finish
        self.manifest = trial_manifest(
            setup.task, "1", setup.values, setup.seed, model_sha256="0" * 64
        )

    async def start(self, socket):
        await asyncio.Event().wait()

    def episode(self):
        return Episode(0, True, "running", "", achieved=False, diverged=False)

    first_tick_at = None
    last_tick_at = None

    async def ended(self):
        await asyncio.Event().wait()

    def metrics(self):
        return {}

    def model_files(self):
        return {}

    async def finish(self, attachments):
        if self.hang_finish:
            await asyncio.Event().wait()
        return ""


class StuckHost(LabHost):
    def __init__(self, hang_finish=False):
        super().__init__()
        self.hang_finish = hang_finish

    def open(self, setup, *, out):
        return StuckLab(setup, self.hang_finish)


class Unused:
    """A sandbox backend the trial never reaches."""

    name = "none"

    def runtime_digest(self):
        return "sha256:none"


def queue_repo(queue, tmp_path, count=1):
    repo = GitRepo.create(tmp_path / "repo", {"lab.toml": LAB_TOML, "c.py": "pass\n"})
    alice = queue.index.user("alice")
    order = Order(
        repository=str(repo.path), ref="main", commit=repo.rev(), task="icreate-maze", public=True
    )
    return [queue.submit(alice, order.episode(n)) for n in range(count)]


async def test_an_exception_in_a_trial_is_an_error_and_the_worker_goes_on(queue, tmp_path):
    """A bug anywhere in a trial files it as an error with the reason; the next one runs."""
    ids = queue_repo(queue, tmp_path, count=2)
    config = WorkerConfig(name="w", work=tmp_path / "work", cache=tmp_path / "cache", poll=0.05)
    w = Worker(queue, BlobStore(str(tmp_path / "blobs")), Unused(), BuggyHost(), config)
    stop = asyncio.Event()
    running = asyncio.create_task(w.run(stop))
    while not all(queue.trial(i).status.ended for i in ids):
        await asyncio.sleep(0.05)
    stop.set()
    await asyncio.wait_for(running, 10)
    for trial_id in ids:
        trial = queue.trial(trial_id)
        assert trial.outcome is Outcome.ERROR
        assert (
            trial.reason
            == "the lab failed while running the trial (RuntimeError: a bug in the lab)"
        )


async def test_a_stuck_trial_is_stopped_at_its_deadline_and_filed(queue, tmp_path):
    """A trial that makes no progress past its stage's deadline ends as an error."""
    [trial_id] = queue_repo(queue, tmp_path)
    options = RunOptions(limits=Limits(wall=0.2), first_step=0.1, grace=0.0, slack=0.0)
    config = WorkerConfig(
        name="w", work=tmp_path / "work", cache=tmp_path / "cache", heartbeat=0.05, options=options
    )
    w = Worker(queue, BlobStore(str(tmp_path / "blobs")), Unused(), StuckHost(), config)
    claim = queue.claim("w")
    assert claim.id == trial_id
    await asyncio.wait_for(w.execute(claim), 20)
    trial = queue.trial(trial_id)
    assert trial.outcome is Outcome.ERROR
    assert trial.reason.startswith("the trial made no progress: it was running for")
    assert w.current is None


async def test_a_worker_stuck_even_in_stopping_loses_its_lease(tmp_path):
    """If stopping a stuck trial hangs too, the heartbeat has stopped: the lease runs out
    and the queue hands the trial to another worker."""
    index = Index.open(f"sqlite:///{tmp_path / 'index.sqlite'}")
    index.add_user("alice", max_running=5)
    queue = Queue(index, QueueConfig(lease=0.5))
    try:
        [trial_id] = queue_repo(queue, tmp_path)
        options = RunOptions(limits=Limits(wall=0.1), first_step=0.1, grace=0.0, slack=0.0)
        config = WorkerConfig(
            name="w",
            work=tmp_path / "work",
            cache=tmp_path / "cache",
            heartbeat=0.05,
            options=options,
        )
        host = StuckHost(hang_finish=True)
        w = Worker(queue, BlobStore(str(tmp_path / "blobs")), Unused(), host, config)
        stuck = asyncio.create_task(w.execute(queue.claim("w")))
        loop = asyncio.get_running_loop()
        deadline = loop.time() + 15
        requeued = []
        while not requeued and loop.time() < deadline:
            await asyncio.sleep(0.1)
            requeued = queue.requeue_expired()
        assert requeued == [trial_id]
        assert queue.trial(trial_id).status is Status.QUEUED
        assert queue.claim("another").id == trial_id
        stuck.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await stuck
    finally:
        index.close()
