"""The HTTP API in process: submissions against real git repositories, the archive's
reads, tokens, and every bad request getting a 4xx that says what to do.

No workers run here: trials stay queued, and finished records are filed the way a
worker files them (blobs in the store, columns in the index).
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import httpx
import pytest

from labd import __version__
from labd.api.app import create_app
from labd.service import Service, ServiceConfig
from labd.sim import registry
from repository.trial import Filing
from scheduler.fetch import FetchPolicy
from scheduler.remote import PROTOCOL, PROTOCOL_HEADER, VERSION_HEADER
from tests.fakes import file_unchecked
from tests.helpers.githttp import GitRepo


@pytest.fixture
def repo(tmp_path) -> Path:
    """A controller repository with two commits and a tag on the first."""
    made = GitRepo.create(
        tmp_path / "controller",
        {"lab.toml": '[controller]\ncommand = ["python", "c.py"]\n', "c.py": "print('one')\n"},
    )
    made.tag("v1")
    made.commit({"c.py": "print('two')\n"}, "two")
    return made.path


@pytest.fixture
def service(tmp_path, sqlite_url):
    config = ServiceConfig(
        data=tmp_path / "data",
        database=sqlite_url,
        workers=0,
        fetch=FetchPolicy(schemes=frozenset({"file"})),
    )
    service = Service(config)
    yield service
    service.index.close()


@pytest.fixture
async def api(service):
    """A client of the API in process; after the test, every answer it got must be one
    the OpenAPI document declares for that route, with the body it declares."""
    woken = []
    app = create_app(service, on_submit=lambda: woken.append(1))
    seen: list[httpx.Response] = []

    async def keep(response):
        await response.aread()
        seen.append(response)

    transport = httpx.ASGITransport(app=app)
    async with httpx.AsyncClient(
        transport=transport, base_url="http://lab.test", event_hooks={"response": [keep]}
    ) as client:
        client.woken = woken
        yield client
    check_declared(app.openapi(), seen)


def check_declared(spec, responses):
    """Each response's status is declared for its route, errors with ``ErrorBody``."""
    routes = [
        (re.compile("^" + re.sub(r"\{[^}]+\}", "[^/]+", path) + "$"), path)
        for path in spec["paths"]
    ]
    for response in responses:
        method = response.request.method.lower()
        url = response.request.url.path
        if url in ("/openapi.json", "/docs", "/redoc"):
            continue
        matched = [path for pattern, path in routes if pattern.match(url)]
        if not matched:
            assert response.status_code == 404, f"{method} {url} is not in the OpenAPI document"
            continue
        operation = spec["paths"][matched[0]].get(method)
        assert operation is not None, f"{method} {url}: no such operation"
        declared = operation["responses"]
        status = str(response.status_code)
        assert status in declared, f"{method} {matched[0]} answered {status}, not declared"
        if response.status_code >= 400:
            schema = declared[status]["content"]["application/json"]["schema"]
            assert schema == {"$ref": "#/components/schemas/ErrorBody"}
            assert set(response.json()) == {"error"}


@pytest.fixture
def token(service):
    return service.index.add_user("alice", max_running=2, max_daily=50)


def auth(token):
    return {"Authorization": f"Bearer {token}"}


async def submit(api, token, repo, **body):
    return await api.post(
        "/api/trials",
        json={"repository": str(repo), "task": "icreate-maze", **body},
        headers=auth(token),
    )


async def test_submit_pins_the_ref_to_a_commit(api, token, repo):
    """A submission answers 201 with the full commit the ref named when it was made."""
    tag = GitRepo(repo).rev("v1")
    reply = await submit(api, token, repo, ref="v1", seed=7, params={"maze_size": "7"})
    assert reply.status_code == 201, reply.text
    trial = reply.json()
    assert trial["commit"] == tag and trial["ref"] == "v1"
    assert trial["status"] == "queued" and trial["seed"] == 7
    assert trial["params"] == {"maze_size": 7}
    assert trial["submitter"] == "alice"
    assert reply.headers["location"].endswith(f"/api/trials/{trial['id']}")
    assert api.woken == [1]
    head = (await submit(api, token, repo)).json()
    assert head["commit"] == GitRepo(repo).rev()
    short = (await submit(api, token, repo, ref=tag[:8])).json()
    assert short["commit"] == tag


@pytest.mark.parametrize(
    ("body", "status", "words"),
    [
        ({"task": "no-such-task"}, 422, "no-such-task"),
        ({"params": {"maze_size": 8}}, 422, "must be odd"),
        ({"params": {"wings": 2}}, 422, "not a parameter"),
        ({"seed": -1}, 422, "seed"),
        ({"ref": "no-such-branch"}, 422, "no-such-branch"),
        ({"repository": "ftp://example.org/x.git"}, 422, "not allowed"),
        ({"repository": "/no/such/repository"}, 422, "/no/such/repository"),
        ({"colour": "blue"}, 422, "colour"),
    ],
)
async def test_bad_submissions_get_a_4xx_and_leave_nothing(api, token, repo, body, status, words):
    """Each bad request is refused with a message naming the problem, and nothing is queued."""
    reply = await submit(api, token, repo, **body)
    assert reply.status_code == status, reply.text
    assert words in reply.json()["error"]
    assert (await api.get("/api/trials")).json()["trials"] == []


async def test_malformed_json_is_a_400(api, token):
    reply = await api.post(
        "/api/trials",
        content=b'{"repository": ',
        headers={**auth(token), "Content-Type": "application/json"},
    )
    assert reply.status_code == 400
    assert "not valid JSON" in reply.json()["error"]


async def test_writing_needs_a_valid_token(api, token, repo):
    """No token or a wrong one is a 401 that says how to get one; reading needs none."""
    missing = await api.post("/api/trials", json={"repository": str(repo), "task": "icreate-maze"})
    assert missing.status_code == 401
    assert "labd users add" in missing.json()["error"]
    wrong = await submit(api, "labd_wrong", repo)
    assert wrong.status_code == 401
    assert (await api.get("/api/trials")).status_code == 200
    assert (await api.post("/api/trials/1/rerun")).status_code == 401


async def test_daily_limit_is_a_429(api, service, repo):
    token = service.index.add_user("bob", max_daily=1)
    assert (await submit(api, token, repo)).status_code == 201
    reply = await submit(api, token, repo)
    assert reply.status_code == 429
    assert "daily limit" in reply.json()["error"]


def file_record(service, trial_id, data: bytes, **columns):
    """File a finished trial as a worker does: claim it, then finish it with a filing."""
    digest = service.store.put_bytes(data)
    claim = service.queue.claim("w")
    assert claim is not None and claim.id == trial_id
    filing = Filing(
        status="finished",
        outcome="success",
        reason="the task was achieved at tick 9",
        mcap=digest,
        mcap_size=len(data),
        data_digest="d" * 64,
        manifest={"schema": "labd.trial/1"},
        metrics={"reward": 1.0, "success": True},
        **columns,
    )
    assert file_unchecked(service, trial_id, "w", filing)
    return digest


async def test_reading_a_trial_and_its_record(api, service, token, repo):
    """A filed trial shows its outcome, and its MCAP downloads byte for byte."""
    trial = (await submit(api, token, repo)).json()
    data = b"\x89MCAP0\r\n" + bytes(range(256)) * 100
    digest = file_record(service, trial["id"], data)
    shown = (await api.get(f"/api/trials/{trial['id']}")).json()
    assert (shown["status"], shown["outcome"]) == ("finished", "success")
    assert shown["reward"] == 1.0
    assert shown["manifest"] == {"schema": "labd.trial/1"}
    assert shown["mcap"]["digest"] == digest and shown["mcap"]["size"] == len(data)
    download = await api.get(f"/api/trials/{trial['id']}/data.mcap")
    assert download.status_code == 200
    assert download.content == data
    assert download.headers["etag"] == f'"{digest}"'
    assert (await api.get("/api/trials/999")).status_code == 404
    assert (await api.get(f"/api/trials/{trial['id']}/logs/stdout")).status_code == 404


async def test_a_damaged_blob_is_never_served(api, service, token, repo):
    """A record whose bytes no longer match its digest is refused, not sent."""
    trial = (await submit(api, token, repo)).json()
    digest = file_record(service, trial["id"], b"record bytes" * 1000)
    hexdigest = digest.removeprefix("sha256:")
    path = Path(service.store.url) / "sha256" / hexdigest[:2] / hexdigest
    path.chmod(0o644)
    path.write_bytes(b"record bytez" * 1000)
    reply = await api.get(f"/api/trials/{trial['id']}/data.mcap")
    assert reply.status_code == 500
    assert "damaged" in reply.json()["error"]


async def test_rerun_cancel_and_the_commit_page(api, service, token, repo):
    """A rerun is a new trial linked to the old; the commit page shows both."""
    trial = (await submit(api, token, repo)).json()
    file_record(service, trial["id"], b"x")
    rerun = await api.post(f"/api/trials/{trial['id']}/rerun", headers=auth(token))
    assert rerun.status_code == 201
    again = rerun.json()
    assert again["rerun_of"] == trial["id"]
    assert (again["commit"], again["seed"]) == (trial["commit"], trial["seed"])
    page = (await api.get(f"/api/commits/{trial['commit'][:10]}")).json()
    assert [t["id"] for t in page["trials"]] == [trial["id"]]
    assert [r["id"] for r in page["trials"][0]["reruns"]] == [again["id"]]
    assert page["rerun_counts"]["pending"] == 1
    cancelled = (await api.post(f"/api/trials/{again['id']}/cancel", headers=auth(token))).json()
    assert cancelled["done"] == "cancelled"
    assert cancelled["trial"]["status"] == "cancelled" and cancelled["trial"]["outcome"] is None
    twice = (await api.post(f"/api/trials/{again['id']}/cancel", headers=auth(token))).json()
    assert twice["done"] == "ended"
    assert (await api.get("/api/commits/zzzz")).status_code == 422
    assert (await api.get("/api/commits/ffffffff")).status_code == 404


async def test_lists_filter_and_page(api, token, repo):
    ids = [(await submit(api, token, repo, seed=s)).json()["id"] for s in range(5)]
    first = (await api.get("/api/trials", params={"limit": 2})).json()
    assert [t["id"] for t in first["trials"]] == ids[:-3:-1]
    second = (await api.get("/api/trials", params={"limit": 2, "before": first["next"]})).json()
    assert [t["id"] for t in second["trials"]] == ids[-3:-5:-1]
    assert (await api.get("/api/trials", params={"status": "queued"})).json()["trials"]
    assert (await api.get("/api/trials", params={"user": "nobody"})).json()["trials"] == []
    bad = await api.get("/api/trials", params={"status": "succeeded"})
    assert bad.status_code == 422 and "status" in bad.json()["error"]
    assert (await api.get("/api/trials", params={"outcome": "success"})).json()["trials"] == []
    bad = await api.get("/api/trials", params={"outcome": "won"})
    assert bad.status_code == 422 and "outcome" in bad.json()["error"]


async def test_openapi_and_tasks(api):
    """Every operation documents its success body and its errors, which are all ErrorBody."""
    spec = (await api.get("/openapi.json")).json()
    for path in ("/api/trials", "/api/trials/{trial_id}/data.mcap", "/api/commits/{sha}"):
        assert path in spec["paths"]
    assert "HTTPValidationError" not in spec["components"]["schemas"]
    for path, operations in spec["paths"].items():
        for method, operation in operations.items():
            for status, answer in operation["responses"].items():
                content = answer.get("content", {})
                if status.startswith("2") and status != "204":
                    assert content, f"{method} {path} {status} has no body schema"
                    for media in content.values():
                        assert media.get("schema") or "json" not in str(media), (method, path)
                if status[0] in "45":
                    assert content["application/json"]["schema"] == {
                        "$ref": "#/components/schemas/ErrorBody"
                    }, (method, path, status)
    listing = (await api.get("/api/tasks")).json()
    tasks = {t["name"]: t for t in listing["tasks"]}
    assert list(tasks) == registry.names() and listing["problems"] == []
    assert {"icreate-maze", "pr2-table", "dmc-cheetah-run"} <= set(tasks)
    assert tasks["icreate-maze"]["params"]["maze_size"]["type"] == "int"


async def test_a_repository_over_the_size_limit_is_a_413(tmp_path, repo):
    """A repository larger than the operator's limit is refused, and no mirror is left."""
    GitRepo(repo).commit({"weights.bin": os.urandom(600_000)}, "weights")
    config = ServiceConfig(
        data=tmp_path / "small",
        workers=0,
        fetch=FetchPolicy(schemes=frozenset({"file"}), max_bytes=200_000),
    )
    service = Service(config)
    token = service.index.add_user("alice")
    transport = httpx.ASGITransport(app=create_app(service, on_submit=lambda: None))
    try:
        async with httpx.AsyncClient(transport=transport, base_url="http://lab.test") as api:
            reply = await submit(api, token, repo)
            assert reply.status_code == 413, reply.text
            assert "limit" in reply.json()["error"]
            assert (await api.get("/api/trials")).json()["trials"] == []
        mirrors = service.cache / "mirrors"
        assert not mirrors.exists() or not any(mirrors.iterdir())
    finally:
        service.index.close()


async def test_a_worker_of_another_version_is_refused_naming_both(api, service):
    """A worker that speaks no or another worker protocol gets a 409 naming both versions,
    before it can claim anything; one of this version is let in."""
    token = service.index.add_user("farm", worker=True)
    old = await api.post("/api/workers/claim", json={"worker": "w1"}, headers=auth(token))
    assert old.status_code == 409
    assert "a labd older than 0.2" in old.json()["error"]
    assert f"this lab is labd {__version__}" in old.json()["error"]
    other = await api.post(
        "/api/workers/claim",
        json={"worker": "w1"},
        headers={**auth(token), PROTOCOL_HEADER: "1", VERSION_HEADER: "0.1.0"},
    )
    assert other.status_code == 409 and "labd 0.1.0" in other.json()["error"]
    same = {**auth(token), PROTOCOL_HEADER: str(PROTOCOL), VERSION_HEADER: __version__}
    hello = await api.get("/api/workers/hello", headers=same)
    assert hello.json() == {
        "version": __version__,
        "protocol": PROTOCOL,
        "worker": "farm",
        "replays": False,  # a worker elsewhere: the lab replays what it files
        "git": None,  # a lab not listening yet has no hosted repositories' URL
    }
    assert (
        await api.post("/api/workers/claim", json={"worker": "w1"}, headers=same)
    ).status_code == 204


async def test_lab_toml_is_checked_at_submit_time_and_names_the_task(api, token, tmp_path):
    """Without a task the submission takes lab.toml's; a missing or broken lab.toml, or one
    that names no task when none is given, is refused as labd run refuses it, and nothing
    is queued."""
    named = GitRepo.create(
        tmp_path / "named",
        {"lab.toml": '[controller]\ncommand = ["python", "c.py"]\ntask = "pr2-table"\n'},
    )
    reply = await api.post("/api/trials", json={"repository": str(named.path)}, headers=auth(token))
    assert reply.status_code == 201, reply.text
    assert reply.json()["task"] == "pr2-table"
    cases = {
        "none": ({"c.py": "print()\n"}, "the repository has no lab.toml at its root"),
        "broken": ({"lab.toml": "[controller\n"}, "lab.toml: it is not valid TOML"),
        "taskless": ({"lab.toml": '[controller]\ncommand = ["python", "c.py"]\n'}, "names no task"),
    }
    for name, (files, words) in cases.items():
        repo = GitRepo.create(tmp_path / name, files)
        reply = await api.post(
            "/api/trials", json={"repository": str(repo.path)}, headers=auth(token)
        )
        assert reply.status_code == 422, reply.text
        assert words in reply.json()["error"]
    assert len((await api.get("/api/trials")).json()["trials"]) == 1


async def test_a_repository_written_two_ways_is_one(api, token, repo):
    """A folder and its file:// URL are recorded alike; a trailing .git finds it too."""
    by_path = (await submit(api, token, repo)).json()
    by_url = (await submit(api, token, f"file://{repo}/")).json()
    assert by_url["repository"] == by_path["repository"] == str(repo)
    for spelling in (str(repo), f"{repo}.git", f"{repo}/"):
        found = (await api.get("/api/trials", params={"repository": spelling})).json()
        assert [t["id"] for t in found["trials"]] == [by_url["id"], by_path["id"]]
