"""``/readyz`` and ``/metrics`` in process: each readiness check failing on its own for a
real cause (an index gone, a store that does not answer, no worker), the metrics parsed
by Prometheus' own parser, held to docs/metrics.md name for name, and the index's counts
read at scrape time equal to what the archive says of each record.

A trial run through a real lab, a bridge client and a driver are in
tests/integration/test_metrics.py.
"""

from __future__ import annotations

import os
import re
import uuid
from pathlib import Path

import httpx
import pytest
import s3fs
import sqlalchemy as sa
from moto.server import ThreadedMotoServer
from prometheus_client.parser import text_string_to_metric_families

from labd.api.app import create_app
from labd.metrics import CONTENT_TYPE
from labd.service import Service, ServiceConfig
from labd.workers import LOCAL_WORKERS
from repository.evaluation_index import Evaluations
from repository.trial import Order, Status
from scheduler.remote import PROTOCOL, PROTOCOL_HEADER
from tests.labd.test_api import check_declared

DOCS = Path(__file__).resolve().parents[2] / "docs" / "metrics.md"
COMMIT = "c" * 40
ASKED = Order(
    repository="https://example.org/r.git",
    ref="main",
    commit=COMMIT,
    task="icreate-maze",
    public=True,
)


class Clock:
    """The lab's clock, moved by the test."""

    def __init__(self) -> None:
        self.now = 1_800_000_000.0

    def __call__(self) -> float:
        return self.now


def make_service(tmp_path: Path, database: str, clock: Clock | None = None, **config) -> Service:
    config.setdefault("workers", 0)
    return Service(
        ServiceConfig(data=tmp_path / "data", database=database, **config), clock=clock or Clock()
    )


@pytest.fixture
def service(tmp_path, sqlite_url):
    service = make_service(tmp_path, sqlite_url)
    yield service
    service.index.close()


class Api:
    """A client of ``service``'s API in process; every answer it got is held to the
    OpenAPI document when it closes."""

    def __init__(self, service: Service) -> None:
        self.app = create_app(service)
        self.seen: list[httpx.Response] = []

        async def keep(response: httpx.Response) -> None:
            await response.aread()
            self.seen.append(response)

        self.client = httpx.AsyncClient(
            transport=httpx.ASGITransport(app=self.app),
            base_url="http://lab.test",
            event_hooks={"response": [keep]},
        )

    async def __aenter__(self) -> httpx.AsyncClient:
        return self.client

    async def __aexit__(self, *exc: object) -> None:
        await self.client.aclose()
        check_declared(self.app.openapi(), self.seen)


async def scrape(api: httpx.AsyncClient) -> dict[str, dict[tuple[tuple[str, str], ...], float]]:
    """``/metrics`` parsed by Prometheus' parser: each sample's value by name and labels."""
    answer = await api.get("/metrics")
    assert answer.status_code == 200
    assert answer.headers["content-type"] == CONTENT_TYPE
    return samples(answer.text)


def samples(text: str) -> dict[str, dict[tuple[tuple[str, str], ...], float]]:
    found: dict[str, dict[tuple[tuple[str, str], ...], float]] = {}
    for family in text_string_to_metric_families(text):
        for sample in family.samples:
            found.setdefault(sample.name, {})[tuple(sorted(sample.labels.items()))] = sample.value
    return found


def documented() -> dict[str, str]:
    """The names and types in docs/metrics.md's table."""
    rows = re.findall(r"^\| `(labd_\w+)` \| (\w+) \|", DOCS.read_text(), re.MULTILINE)
    return dict(rows)


# -- /readyz ------------------------------------------------------------------------------


async def test_a_lab_without_workers_of_its_own_is_ready_and_says_so(service):
    """/readyz answers 200 with what each check found; a lab of remote workers only is
    ready before any has come, saying that trials wait for one."""
    async with Api(service) as api:
        ready = await api.get("/readyz")
        alive = await api.get("/healthz")
    assert ready.status_code == 200, ready.text
    body = ready.json()
    assert body["status"] == "ready" and set(body["checks"]) == {"index", "store", "workers"}
    assert body["checks"]["index"].startswith("the SQLite index answers")
    assert body["checks"]["store"] == "the local blob store answers"
    assert "no workers of its own" in body["checks"]["workers"]
    assert alive.json() == {"status": "ok", "checks": {}}


async def test_readyz_is_503_naming_the_index_when_it_is_gone(tmp_path, database_url):
    """An index that stops answering (PostgreSQL's database dropped under the lab; SQLite's
    log deleted) makes /readyz 503 naming the index, and the metrics say labd_index_up 0
    and still answer the rest."""
    service = make_service(tmp_path, database_url)
    try:
        async with Api(service) as api:
            assert (await api.get("/readyz")).status_code == 200
            if database_url.startswith("sqlite"):
                (tmp_path / "index.sqlite-wal").unlink()
            else:
                admin = sa.create_engine(
                    os.environ["LABD_TEST_POSTGRES_URL"], isolation_level="AUTOCOMMIT"
                )
                with admin.connect() as db:
                    name = database_url.rsplit("/", 1)[1]
                    db.execute(sa.text(f'DROP DATABASE "{name}" WITH (FORCE)'))
                admin.dispose()
            ready = await api.get("/readyz")
            found = await scrape(api)
    finally:
        service.index.close()
    assert ready.status_code == 503, ready.text
    error = ready.json()["error"]
    assert error.startswith("not ready: index: ") and "store" not in error, error
    assert found["labd_index_up"] == {(): 0.0}
    assert "labd_workers" in found
    # Read, when it can be (the SQLite file is still there: only writes are refused).
    assert ("labd_trials" in found) is database_url.startswith("sqlite")


async def test_readyz_is_503_naming_a_local_store_it_cannot_write_in(tmp_path, sqlite_url):
    """A blob store whose folder is under a file (a mount gone wrong) is a 503 naming the
    store, and only it."""
    (tmp_path / "mount").write_text("not a folder")
    service = make_service(tmp_path, sqlite_url, blobs=str(tmp_path / "mount" / "blobs"))
    try:
        async with Api(service) as api:
            ready = await api.get("/readyz")
    finally:
        service.index.close()
    assert ready.status_code == 503
    error = ready.json()["error"]
    assert error.startswith("not ready: store: the local blob store does not answer"), error
    assert "index" not in error and "workers" not in error


async def test_readyz_follows_an_s3_store(tmp_path, sqlite_url, monkeypatch):
    """An S3-compatible store (a real one: moto) that answers, empty and then holding a
    blob, is ready; once its server is gone, /readyz is a 503 naming the store."""
    server = ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
    server.start()
    host, port = server.get_host_and_port()
    endpoint = f"http://{host}:{port}"
    monkeypatch.setenv("AWS_ACCESS_KEY_ID", "testing")
    monkeypatch.setenv("AWS_SECRET_ACCESS_KEY", "testing")
    # moto keeps its buckets per process, across servers: a name of this test's own
    bucket = f"lab-readyz-{uuid.uuid4().hex[:12]}"
    s3fs.S3FileSystem(endpoint_url=endpoint, key="testing", secret="testing").mkdir(bucket)
    options = {"endpoint_url": endpoint, "key": "testing", "secret": "testing"}
    options["config_kwargs"] = {"retries": {"max_attempts": 1}}  # fail fast once it is gone
    blobs = f"s3://{bucket}/blobs"
    service = make_service(tmp_path, sqlite_url, blobs=blobs, blob_options=options)
    try:
        async with Api(service) as api:
            empty = await api.get("/readyz")
            service.store.put_bytes(b"a blob")
            holding = await api.get("/readyz")
            server.stop()
            gone = await api.get("/readyz")
    finally:
        service.index.close()
    assert empty.status_code == 200 and holding.status_code == 200, holding.text
    assert holding.json()["checks"]["store"] == "the s3 blob store answers"
    assert gone.status_code == 503
    assert gone.json()["error"].startswith("not ready: store: the s3 blob store does not answer")


async def test_readyz_needs_a_worker_when_the_lab_runs_its_own(tmp_path, sqlite_url):
    """A lab that runs workers is not ready before one can run trials; a remote worker
    that claims makes it ready, one that is out of the pool (a canary diverged) or has
    not been heard from for a lease does not, and the metrics count each state."""
    clock = Clock()
    service = make_service(tmp_path, sqlite_url, workers=1, clock=clock)
    token = service.index.add_user("farm", worker=True)
    headers = {"Authorization": f"Bearer {token}", PROTOCOL_HEADER: str(PROTOCOL)}
    try:
        async with Api(service) as api:
            unstarted = await api.get("/readyz")
            claimed = await api.post("/api/workers/claim", json={"worker": "w1"}, headers=headers)
            ready = await api.get("/readyz")
            one = (await scrape(api))["labd_workers"]
            clock.now += service.queue.config.lease + 1
            quiet = await api.get("/readyz")
            lost = (await scrape(api))["labd_workers"]
            await api.post("/api/workers/claim", json={"worker": "w1"}, headers=headers)
            report = {"worker": "w1", "state": "out", "detail": "canary 3 diverged"}
            await api.post("/api/workers/health", json=report, headers=headers)
            out = await api.get("/readyz")
            counted = (await scrape(api))["labd_workers"]
    finally:
        service.index.close()
    assert unstarted.status_code == 503
    assert "workers: no worker can run trials (none started yet)" in unstarted.json()["error"]
    assert claimed.status_code == 204
    assert ready.status_code == 200 and ready.json()["checks"]["workers"] == (
        "workers ready: 1 remote"
    )
    assert one[(("kind", "remote"), ("state", "ok"))] == 1
    assert quiet.status_code == 503 and "1 remote lost" in quiet.json()["error"]
    assert lost[(("kind", "remote"), ("state", "lost"))] == 1
    assert out.status_code == 503 and "1 remote out" in out.json()["error"]
    assert counted[(("kind", "remote"), ("state", "out"))] == 1
    assert sum(counted.values()) == 1
    assert "farm" not in out.text and "w1" not in out.text  # counts, never names


# -- /metrics -----------------------------------------------------------------------------


async def test_every_metric_is_documented_and_every_documented_metric_is_there(service):
    """The families /metrics answers are docs/metrics.md's table, name for name and type
    for type (a counter by its ``_total`` name; the histogram's ``_created`` beside it)."""
    async with Api(service) as api:
        answer = await api.get("/metrics")
    docs = documented()
    assert len(docs) >= 15
    shown: dict[str, str] = {}
    for family in text_string_to_metric_families(answer.text):
        name = family.name + ("_total" if family.type == "counter" else "")
        if name.endswith("_created") and name.removesuffix("_created") in docs:
            continue
        shown[name] = family.type
    assert shown == docs


async def test_the_index_is_counted_as_the_archive_reads_it(tmp_path, database_url):
    """Trials by kind, status and outcome, the queue's depth and oldest wait, reruns by
    verdict, and evaluations by status (each as the archive's own record of it says:
    queued, running, finished, cancelled) are what the metrics read, on SQLite and
    PostgreSQL."""
    clock = Clock()
    service = make_service(tmp_path, database_url, clock=clock)
    index = service.index
    evaluations: Evaluations = service.evaluations
    try:
        made = [evaluate(service, seeds=3) for _ in range(5)]
        trials = [evaluations.trials(e) for e in made]
        # made[0] stays queued; made[1] runs; made[2] finished; made[3] was cancelled while
        # running; made[4] was asked to stop after it had finished (finished, not cancelled).
        index.update(trials[1][0], status="running", started=clock.now)
        for trial in trials[2] + trials[4]:
            index.update(trial, status="finished", outcome="success", finished=clock.now)
        index.update(trials[3][0], status="finished", outcome="fail", finished=clock.now)
        for trial in trials[3][1:]:
            index.update(trial, status="cancelled", finished=clock.now)
        with index.begin() as db:
            evaluation_table = sa.table(
                "evaluations", sa.column("id"), sa.column("cancel_requested"), sa.column("finished")
            )
            db.execute(
                sa.update(evaluation_table)
                .where(evaluation_table.c.id.in_([made[3], made[4]]))
                .values(cancel_requested=True)
            )
            db.execute(
                sa.update(evaluation_table)
                .where(evaluation_table.c.id.in_([made[2], made[4]]))
                .values(finished=clock.now)
            )
        again = ASKED.model_copy(update={"rerun_of": trials[2][0]})
        rerun = index.add_trial(again, submitter="alice")
        index.update(rerun, status="finished", outcome="success", reproduced=False)
        clock.now += 90
        statuses = {e: evaluations.get(e).status for e in made}
        async with Api(service) as api:
            found = await scrape(api)
    finally:
        index.close()
    assert [statuses[e] for e in made] == [
        Status.QUEUED,
        Status.RUNNING,
        Status.FINISHED,
        Status.CANCELLED,
        Status.FINISHED,
    ]
    evaluated = {dict(k)["status"]: v for k, v in found["labd_evaluations"].items()}
    assert evaluated == {"queued": 1, "running": 1, "finished": 2, "cancelled": 1}
    trials_ = {
        tuple(dict(k)[n] for n in ("kind", "status", "outcome")): v
        for k, v in found["labd_trials"].items()
        if v
    }
    assert trials_ == {
        ("trial", "queued", ""): 5,  # made[0]'s 3, made[1]'s 2
        ("trial", "running", ""): 1,
        ("trial", "finished", "success"): 7,  # made[2]'s 3, made[4]'s 3, the rerun
        ("trial", "finished", "fail"): 1,
        ("trial", "cancelled", ""): 2,
    }
    assert found["labd_queue_depth"] == {(): 5.0}
    assert found["labd_queue_oldest_wait_seconds"] == {(): 90.0}
    assert found["labd_reruns"] == {(("verdict", "diverged"),): 1, (("verdict", "reproduced"),): 0}
    assert found["labd_index_up"] == {(): 1.0}


def evaluate(service: Service, *, seeds: int) -> int:
    """An evaluation of ``seeds`` episodes, queued, as the evaluator writes one."""
    index = service.index
    with index.begin() as db:
        ids = [
            index.add_trial(ASKED.episode(seed), submitter="alice", db=db) for seed in range(seeds)
        ]
        return service.evaluations.add(
            db,
            ASKED,
            submitter="alice",
            task_version="1",
            suite="dev",
            suite_version=1,
            held_out=False,
            seeds=list(range(seeds)),
            trial_ids=ids,
        )


async def test_the_blob_stores_errors_are_counted(service):
    """A damaged blob read (its download refused) counts as ``corrupt``, a write the disk
    refuses as ``write``; a blob that is not there counts as nothing."""
    digest = service.store.put_bytes(b"the record's bytes")
    held = service.index.add_trial(ASKED, submitter="alice")  # a record anyone may read
    service.index.update(held, status="finished", outcome="success", mcap=digest)
    path = Path(service.store.path(digest))
    path.chmod(0o644)
    path.write_bytes(b"the record's bytez")
    async with Api(service) as api:
        damaged = await api.get(f"/api/blobs/{digest}")
        missing = await api.get(f"/api/blobs/sha256:{'0' * 64}")
        tmp = Path(service.store.path(digest)).parents[2] / "tmp"
        tmp.rmdir()
        tmp.write_text("a file where the store writes its temporary files")
        with pytest.raises(OSError):
            service.store.put_bytes(b"new bytes")
        found = (await scrape(api))["labd_blob_store_errors_total"]
    assert (damaged.status_code, missing.status_code) == (500, 404)
    errors = {dict(k)["operation"]: v for k, v in found.items()}
    assert errors == {"corrupt": 1, "write": 1, "read": 0}


async def test_the_labs_worker_processes_are_counted_apart_from_remote_ones(tmp_path, sqlite_url):
    """A worker of the lab's own processes (the ``local-workers`` account) is counted as
    ``process``, and makes a lab that runs worker processes ready; a remote one as
    ``remote``."""
    service = make_service(tmp_path, sqlite_url, worker_processes=1)
    try:
        async with Api(service) as api:
            unready = await api.get("/readyz")
            for user in (LOCAL_WORKERS, "farm"):
                token = service.index.add_user(user, worker=True)
                headers = {"Authorization": f"Bearer {token}", PROTOCOL_HEADER: str(PROTOCOL)}
                await api.post("/api/workers/claim", json={"worker": "w1"}, headers=headers)
            ready = await api.get("/readyz")
            counted = (await scrape(api))["labd_workers"]
    finally:
        service.index.close()
    assert unready.status_code == 503
    assert ready.json()["checks"]["workers"] == "workers ready: 1 in processes, 1 remote"
    assert {dict(k)["kind"]: v for k, v in counted.items() if v} == {"process": 1, "remote": 1}
