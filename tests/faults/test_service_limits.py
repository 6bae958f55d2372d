"""The service's quotas, leases and deadlines, hit at their documented values.

docs/service.md and docs/trials.md promise them: a user's 500 submissions a day and 2
trials at once, three lost leases before a trial is given up, a page of at most 500
trials; and a deadline for each stage of a trial, here met by real slow conditions (a
package index that does not answer, an S3 server that is stopped) with the deadlines
shortened, since the real ones are minutes long (their values are checked against the
docs in test_documented_defaults).
"""

from __future__ import annotations

import asyncio
from pathlib import Path
from typing import Any

import httpx
import psutil
import pytest

from labd.api.app import create_app
from labd.service import Service, ServiceConfig
from repository.blobs import BlobStore
from repository.index import Index, connect
from repository.trial import Order, Outcome, Status
from scheduler.errors import QuotaExceeded
from scheduler.queue import Queue, QueueConfig
from scheduler.runner import RunOptions, run_trial
from scheduler.worker import Worker, WorkerConfig
from tests.fakes import WallClock
from tests.faults.conftest import gone
from tests.faults.slow import PackageIndex, S3Server, controller
from tests.helpers.githttp import GitRepo
from tests.helpers.sandboxes import make_backend

pytestmark = pytest.mark.integration


@pytest.fixture
def queue(database_url: str, clock: WallClock):
    """The queue with its default configuration, and a user with the default limits."""
    db = Index(connect(database_url), clock=clock)
    db.create()
    db.add_user("alice")
    yield Queue(db)
    db.close()


def submit(queue: Queue, seed: int = 0) -> int:
    order = Order(
        repository="https://example.org/r.git",
        ref="main",
        commit="a" * 40,
        task="icreate-maze",
        seed=seed,
        public=True,
    )
    return queue.submit(queue.index.user("alice"), order)


def test_a_user_submits_at_most_500_trials_a_day(queue: Queue, clock: WallClock):
    """The 501st submission within 24 hours is refused, saying why; a day later it is not."""
    for n in range(500):
        submit(queue, n)
    with pytest.raises(QuotaExceeded) as refused:
        submit(queue, 500)
    assert str(refused.value).startswith(
        "alice has submitted 500 trials in the last 24 hours, the daily limit"
    )
    clock.now += 86_401
    submit(queue, 500)


def test_a_user_runs_at_most_2_trials_at_once(queue: Queue):
    """A third trial of the same user waits until one of the two running ends."""
    ids = [submit(queue, n) for n in range(3)]
    assert [queue.claim(f"w{n}").id for n in range(2)] == ids[:2]
    assert queue.claim("w2") is None
    assert queue.queued() == 1


def test_three_lost_leases_end_a_trial_as_an_error(queue: Queue, clock: WallClock):
    """A trial whose worker is lost three times (30 s leases run out) is given up, saying so."""
    trial = submit(queue)
    for attempt in (1, 2, 3):
        claim = queue.claim("w")
        assert (claim.id, claim.attempt) == (trial, attempt)
        clock.now += 29
        assert queue.requeue_expired() == []  # within its lease: still the worker's
        clock.now += 2
    assert queue.claim("w") is None
    row = queue.index.trial(trial)
    assert (row.status, row.outcome, row.attempts) == (Status.FINISHED, Outcome.ERROR, 3)
    assert row.reason == "its worker was lost 3 times; the lab gave up"


async def test_a_page_of_trials_is_at_most_500(tmp_path: Path):
    """GET /api/trials takes a limit up to 500; 501 is a 422 that says so."""
    service = Service(ServiceConfig(data=tmp_path / "data", workers=0))
    transport = httpx.ASGITransport(app=create_app(service))
    try:
        async with httpx.AsyncClient(transport=transport, base_url="http://lab.test") as api:
            assert (await api.get("/api/trials?limit=500")).status_code == 200
            refused = await api.get("/api/trials?limit=501")
            assert refused.status_code == 422
            assert refused.json()["error"] == "limit: Input should be less than or equal to 500"
    finally:
        service.index.close()


# -- stage deadlines, met by real slow conditions --------------------------------------------


@pytest.mark.timeout(90)
def test_preparing_past_its_deadline_is_an_error(
    cache, host, held_package_index: PackageIndex, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
):
    """Requirements whose index does not answer: the trial ends at the preparing deadline
    as an error saying which stage took too long, and the installer's sandbox is stopped."""
    monkeypatch.setenv("PIP_INDEX_URL", held_package_index.url)
    repo = GitRepo.create(tmp_path / "needs", controller(3, requirements=True))
    backend = make_backend("bwrap", cache)
    order = Order(repository=str(repo.path))
    options = RunOptions(prepare=8.0)

    async def run() -> Any:
        out = tmp_path / "out"
        # children from before (helper processes other tests in this process started)
        # are not the installer's
        before = {p.pid for p in psutil.Process().children(recursive=True)}
        trial = asyncio.create_task(
            run_trial(order, backend=backend, host=host, out=out, cache=cache, options=options)
        )
        asked = asyncio.create_task(asyncio.to_thread(held_package_index.asked.wait, 60))
        await asyncio.wait({trial, asked}, return_when=asyncio.FIRST_COMPLETED)
        installer = [  # pip, waiting for the index, and its sandbox
            p for p in psutil.Process().children(recursive=True) if p.pid not in before
        ]
        assert held_package_index.asked.is_set() and installer, "pip never asked the index"
        ended = await trial
        # While the lab goes on (this loop still runs), the installer is gone.
        await asyncio.to_thread(gone, installer, 10)
        return ended

    result = asyncio.run(run())
    assert result.outcome is Outcome.ERROR
    assert result.reason == (
        "preparing the trial (checking out, reading lab.toml, installing the requirements,"
        " fetching its data) took longer than 8 s"
    )


def quick_trial_on_s3(
    tmp_path: Path, s3: S3Server, config: QueueConfig
) -> tuple[Index, Queue, int, BlobStore]:
    """A queue with one short maze trial submitted, and a blob store in ``s3``."""
    db = Index.open(f"sqlite:///{tmp_path / 'index.sqlite'}")
    db.add_user("alice")
    queue = Queue(db, config)
    repo = GitRepo.create(tmp_path / "quick", controller(3))
    order = Order(
        repository=str(repo.path), ref="main", commit=repo.rev(), task="icreate-maze", public=True
    )
    trial = queue.submit(db.user("alice"), order)
    store = BlobStore(
        "s3://lab-archive/records",
        {"endpoint_url": s3.url, "key": "testing", "secret": "testing"},
    )
    return db, queue, trial, store


@pytest.mark.timeout(90)
def test_filing_past_its_deadline_is_an_error(cache, host, s3: S3Server, tmp_path: Path):
    """A record the stopped store does not take within the filing deadline: the trial is
    filed as an error saying so, and the worker is free again."""
    db, queue, trial, store = quick_trial_on_s3(tmp_path, s3, QueueConfig())
    config = WorkerConfig(name="w", work=tmp_path / "work", cache=cache, filing=3.0)
    worker = Worker(queue, store, make_backend("bwrap", cache), host, config)

    async def run() -> None:
        s3.pause()
        try:
            await asyncio.wait_for(worker.execute(queue.claim("w")), 60)
        finally:
            s3.resume()  # the upload's thread, still waiting, may finish now

    asyncio.run(run())
    row = db.trial(trial)
    assert (row.status, row.outcome) == (Status.FINISHED, Outcome.ERROR)
    assert row.reason == "the archive did not store the record within 3 s"
    assert row.mcap is None and worker.current is None
    db.close()


@pytest.mark.timeout(90)
def test_a_filing_slower_than_the_lease_keeps_its_trial(cache, host, s3: S3Server, tmp_path: Path):
    """A record that takes longer to store than a lease lasts (the store is stopped for 4
    leases): its worker keeps renewing the lease while filing, so another worker that
    claims meanwhile never gets the trial, and it is filed once, on its first attempt."""
    db, queue, trial, store = quick_trial_on_s3(tmp_path, s3, QueueConfig(lease=1.0))
    config = WorkerConfig(name="w1", work=tmp_path / "work", cache=cache, heartbeat=0.25)
    worker = Worker(queue, store, make_backend("bwrap", cache), host, config)
    taken: list[object] = []

    async def run() -> None:
        s3.pause()
        filing = asyncio.create_task(worker.execute(queue.claim("w1")))
        while worker.current is None or worker.current.stage != "filing":
            await asyncio.sleep(0.05)
        for _ in range(40):  # another worker claims every 0.1 s for 4 s
            taken.append(await asyncio.to_thread(queue.claim, "w2"))
            await asyncio.sleep(0.1)
        s3.resume()
        await asyncio.wait_for(filing, 60)

    asyncio.run(run())
    assert taken == [None] * 40
    row = db.trial(trial)
    assert (row.status, row.outcome, row.attempts, row.worker) == (
        Status.FINISHED,
        Outcome.FAIL,
        1,
        "w1",
    )
    assert row.mcap is not None and store.exists(row.mcap)
    db.close()
