"""A record's summary over the API: made once and kept, served gzip'd, declared in the
OpenAPI document; and filed by a worker on another machine through its own endpoint."""

from __future__ import annotations

import gzip
import hashlib
import threading

import orjson
import pytest
import uvicorn

from labd.api.app import create_app
from labd.recorder.summary import VERSION
from repository.errors import RecordNotFound
from repository.index import Derived
from repository.trial import Filing, Order
from repository.well_known import SUMMARY, SUMMARY_MEDIA_TYPE
from scheduler.remote import PROTOCOL, PROTOCOL_HEADER, RemoteLab
from tests.fakes import file_unchecked
from tests.labd.test_api import api, service  # noqa: F401  (fixtures)
from tests.labd.test_summary import drive, twist

PATH = "/api/trials/{}/summary"


@pytest.fixture(scope="module")
def record(registry, tmp_path_factory):
    """A short maze drive, recorded as a trial records it."""
    folder = tmp_path_factory.mktemp("record")
    made = drive(registry, folder, "icreate-maze", 12, lambda k: [twist(0.2, 0.5)])
    made.robot.close()
    return made.path


def file_trial(service, record, worker="w"):  # noqa: F811
    """A finished trial with ``record`` as its MCAP, filed by ``worker``."""
    user = _alice(service)
    order = Order(repository="/r", commit="c" * 40, task="icreate-maze", seed=3, public=True)
    trial_id = service.queue.submit(user, order)
    assert service.queue.claim(worker).id == trial_id
    digest = service.store.put_file(record)
    filing = Filing(
        status="finished", outcome="fail", reason="ran out of time", mcap=digest,
        mcap_size=record.stat().st_size, data_digest="d" * 64,
    )  # fmt: skip
    assert file_unchecked(service, trial_id, worker, filing)
    return trial_id


def _alice(service):  # noqa: F811
    try:
        return service.index.user("alice")
    except RecordNotFound:
        service.index.add_user("alice", max_running=5)
        return service.index.user("alice")


async def test_a_summary_is_made_once_then_served_from_the_store(api, service, record):  # noqa: F811
    """The first request makes the summary from the record and keeps it beside it; the
    next is served from the store, the same bytes, gzip'd for a browser that takes gzip."""
    trial_id = file_trial(service, record)
    assert SUMMARY not in service.index.derived(trial_id)
    first = await api.get(PATH.format(trial_id), headers={"Accept-Encoding": "gzip"})
    assert first.status_code == 200 and first.headers["content-encoding"] == "gzip"
    assert first.headers["content-type"] == "application/json"
    summary = first.json()
    assert summary["version"] == VERSION and summary["ticks"] == 13 and summary["map"]["walls"]
    kept = service.index.derived(trial_id)[SUMMARY]
    assert kept.media_type == SUMMARY_MEDIA_TYPE
    assert gzip.decompress(service.store.read_bytes(kept.digest)) == first.content
    again = await api.get(PATH.format(trial_id), headers={"Accept-Encoding": "identity"})
    assert "content-encoding" not in again.headers and again.content == first.content
    assert service.index.derived(trial_id)[SUMMARY] == kept


async def test_a_summary_of_an_older_version_is_made_again(api, service, record):  # noqa: F811
    trial_id = file_trial(service, record)
    old = gzip.compress(orjson.dumps({"version": 0}))
    digest = service.store.put_bytes(old)
    service.index.put_derived(trial_id, Derived(SUMMARY, digest, len(old), SUMMARY_MEDIA_TYPE))
    answer = await api.get(PATH.format(trial_id))
    assert answer.json()["version"] == VERSION
    assert service.index.derived(trial_id)[SUMMARY].digest != digest


async def test_no_record_no_summary(api, service):  # noqa: F811
    """A trial without a record, and no trial at all, are 404s that say so."""
    user = _alice(service)
    queued = service.queue.submit(
        user, Order(repository="/r", commit="c" * 40, task="icreate-maze", public=True)
    )
    answer = await api.get(PATH.format(queued))
    assert answer.status_code == 404 and "no record" in answer.json()["error"]
    assert (await api.get(PATH.format(424242))).status_code == 404


async def test_the_summary_is_described_in_the_openapi_document(api):  # noqa: F811
    spec = (await api.get("/openapi.json")).json()
    answers = spec["paths"]["/api/trials/{trial_id}/summary"]["get"]["responses"]
    schema = answers["200"]["content"]["application/json"]["schema"]
    assert schema == {"$ref": "#/components/schemas/RecordSummary"}
    fields = spec["components"]["schemas"]["RecordSummary"]["properties"]
    assert {"version", "t", "plots", "camera", "map", "scene"} <= set(fields)


def worker_headers(token):
    return {"Authorization": f"Bearer {token}", PROTOCOL_HEADER: str(PROTOCOL)}


async def test_a_remote_worker_files_the_summary_of_its_own_trials_only(api, service, record):  # noqa: F811
    """Its blob uploaded (checked against its digest), a worker files a summary of a trial
    it filed; another worker's trial, another name or a missing blob are refused."""
    token = service.index.add_user("farm", worker=True)
    mine = file_trial(service, record, worker="farm@w1")
    theirs = file_trial(service, record, worker="farm@w2")
    blob = gzip.compress(orjson.dumps({"version": VERSION}))
    digest = f"sha256:{hashlib.sha256(blob).hexdigest()}"
    headers = worker_headers(token)
    wrong = await api.put(f"/api/blobs/sha256:{'0' * 64}", content=blob, headers=headers)
    assert wrong.status_code == 422
    item = {"name": SUMMARY, "digest": digest, "size": len(blob), "media_type": SUMMARY_MEDIA_TYPE}
    path = "/api/workers/trials/{}/derived"
    early = await api.post(path.format(mine), json={"worker": "w1", "item": item}, headers=headers)
    assert early.status_code == 422 and "upload" in early.json()["error"]
    assert (await api.put(f"/api/blobs/{digest}", content=blob, headers=headers)).status_code == 201
    other = {**item, "name": "export.parquet"}
    refused = await api.post(
        path.format(mine), json={"worker": "w1", "item": other}, headers=headers
    )
    assert refused.status_code == 422
    filed = await api.post(path.format(mine), json={"worker": "w1", "item": item}, headers=headers)
    assert filed.json() == {"filed": True}
    assert service.index.derived(mine)[SUMMARY].digest == digest
    stolen = await api.post(
        path.format(theirs), json={"worker": "w1", "item": item}, headers=headers
    )
    assert stolen.json() == {"filed": False} and SUMMARY not in service.index.derived(theirs)


@pytest.fixture
def http(service):  # noqa: F811
    """The lab's API served on 127.0.0.1 (a port of its own), for a real HTTP client."""
    server = uvicorn.Server(
        uvicorn.Config(create_app(service), host="127.0.0.1", port=0, log_level="warning")
    )
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    while not server.started:
        thread.join(0.02)
    port = server.servers[0].sockets[0].getsockname()[1]
    yield f"http://127.0.0.1:{port}"
    server.should_exit = True
    thread.join(10)


def test_remote_lab_derive_speaks_the_endpoint(service, record, http, tmp_path):  # noqa: F811
    """``RemoteLab`` (``labd worker``) uploads the blob and files it through the API."""
    token = service.index.add_user("farm", worker=True)
    trial_id = file_trial(service, record, worker="farm@w1")
    remote = RemoteLab(http, token)
    path = tmp_path / SUMMARY
    path.write_bytes(gzip.compress(b'{"version":1}'))
    digest = remote.put_file(path)
    item = Derived(SUMMARY, digest, path.stat().st_size, SUMMARY_MEDIA_TYPE)
    assert remote.derive(trial_id, "w1", item) is True
    assert service.index.derived(trial_id)[SUMMARY] == item
    remote.close()
