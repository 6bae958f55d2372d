"""The API's edges in process: who may write is known before a body is read, bodies have
a limit per route, and ids and digests are checked where they come in.

(tests/faults/test_api_attacks.py makes the same attacks on a real `labd serve`.)
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import httpx
import pytest
from fastapi.routing import APIRoute

from labd import __version__
from labd.api.common import _writer
from labd.api.edges import BODY_LIMIT, limit
from labd.api.workers import MAX_BLOB
from labd.service import Service, ServiceConfig
from labd.web import Site, create_app
from repository.trial import MAX_ID
from scheduler.remote import PROTOCOL, PROTOCOL_HEADER, VERSION_HEADER

DIGEST = "sha256:" + "0" * 64


@pytest.fixture
def service(tmp_path):
    service = Service(ServiceConfig(data=tmp_path / "data", workers=0))
    yield service
    service.index.close()


@pytest.fixture
def app(service):
    return create_app(service, Site(), on_submit=lambda: None)


async def call(app: Any, method: str, path: str, headers: dict[str, str], body: bytes) -> tuple:
    """Send one request to ``app`` as a server would, the body in 64 KiB messages, and
    return (status, headers, body, bytes of the body the app read)."""
    scope = {
        "type": "http",
        "asgi": {"version": "3.0"},
        "http_version": "1.1",
        "method": method,
        "path": path,
        "raw_path": path.encode(),
        "root_path": "",
        "scheme": "http",
        "query_string": b"",
        "headers": [(k.lower().encode(), v.encode()) for k, v in headers.items()],
        "client": ("127.0.0.1", 1),
        "server": ("lab.test", 80),
    }
    pieces = [body[i : i + 65536] for i in range(0, len(body), 65536)] or [b""]
    read = 0
    sent: list[dict[str, Any]] = []

    async def receive() -> dict[str, Any]:
        nonlocal read
        if not pieces:
            return {"type": "http.disconnect"}
        piece = pieces.pop(0)
        read += len(piece)
        return {"type": "http.request", "body": piece, "more_body": bool(pieces)}

    async def send(message: dict[str, Any]) -> None:
        sent.append(message)

    await app(scope, receive, send)
    start = sent[0]
    answer = b"".join(m.get("body", b"") for m in sent[1:])
    return (
        start["status"],
        dict((k.decode(), v.decode()) for k, v in start["headers"]),
        answer,
        read,
    )


def test_every_write_to_the_api_needs_a_writer(app):
    """Each route under /api/ that takes anything but GET, HEAD or OPTIONS depends on the
    ``Writer`` (so refusing others before their body is read refuses nobody it should
    serve)."""

    def depends(dependant: Any) -> bool:
        return any(d.call is _writer or depends(d) for d in dependant.dependencies)

    writes = [
        (method, route)
        for route in _leaves(app.routes)
        if route.path.startswith("/api/")
        for method in route.methods - {"GET", "HEAD", "OPTIONS"}
    ]
    assert len(writes) >= 14, writes  # submit, rerun, cancel, the workers', tokens, bookings
    public = [f"{m} {r.path}" for m, r in writes if not depends(r.dependant)]
    assert public == []


def _leaves(routes: list[Any]) -> Iterator[APIRoute]:
    """The API routes of an app, through the routers it includes."""
    for route in routes:
        included = getattr(route, "original_router", None)
        if included is not None:
            yield from _leaves(included.routes)
        elif isinstance(route, APIRoute):
            yield route


async def test_an_anonymous_write_is_refused_before_its_body_is_read(app):
    """A submission with no token is a 401 that closes the connection, having read none of
    its 3 MiB body; with an unknown token, the same."""
    body = b'{"repository": "' + b"x" * (3 << 20) + b'"}'
    for headers in ({}, {"Authorization": "Bearer labd_nobody"}):
        status, sent, answer, read = await call(app, "POST", "/api/trials", headers, body)
        assert status == 401, answer
        assert read == 0
        assert sent["connection"] == "close"
        assert b"token" in answer


async def test_a_body_over_its_routes_limit_is_a_413(app, service):
    """A writer's JSON body over 1 MiB is a 413 naming the limit: from its Content-Length
    with nothing read, and without one once 1 MiB has come; a worker's blob upload is
    held to its own limit (4 GiB), not the JSON bodies'."""
    token = service.index.add_user("alice", worker=True)
    auth = {"Authorization": f"Bearer {token}", "Content-Type": "application/json"}
    body = b'{"repository": "' + b"x" * (3 << 20) + b'"}'
    declared = {**auth, "Content-Length": str(len(body))}
    status, sent, answer, read = await call(app, "POST", "/api/trials", declared, body)
    assert (status, read) == (413, 0), answer
    assert b"(1 MiB)" in answer
    status, sent, answer, read = await call(app, "POST", "/api/trials", auth, body)
    assert status == 413, answer
    assert BODY_LIMIT < read <= BODY_LIMIT + 65536
    assert sent["connection"] == "close"
    worker = {
        **auth,
        PROTOCOL_HEADER: str(PROTOCOL),
        VERSION_HEADER: __version__,
        "Content-Length": str(MAX_BLOB + 1),
    }
    status, _, answer, read = await call(app, "PUT", f"/api/blobs/{DIGEST}", worker, b"x")
    assert (status, read) == (413, 0), answer
    assert b"(4 GiB)" in answer
    assert limit("PUT", f"/api/blobs/{DIGEST}") == MAX_BLOB
    assert limit("POST", "/session") == BODY_LIMIT


async def test_a_form_over_1_mib_is_a_413(app):
    """The pages' forms are held to the same 1 MiB (a sign-in needs no account, so its
    body is the one an anonymous client can send)."""
    form = {"Content-Type": "application/x-www-form-urlencoded"}
    status, _, answer, _ = await call(app, "POST", "/session", form, b"name=" + b"a" * (2 << 20))
    assert status == 413, answer


async def test_ids_and_digests_are_bounded_in_the_openapi_document(app):
    """The OpenAPI document gives every id its range and a blob's digest its pattern, and
    an id past the range is a 422 saying so."""
    async with httpx.AsyncClient(
        transport=httpx.ASGITransport(app=app), base_url="http://lab.test"
    ) as client:
        spec = (await client.get("/openapi.json")).json()
        (trial_id,) = spec["paths"]["/api/trials/{trial_id}"]["get"]["parameters"]
        assert trial_id["schema"]["maximum"] == MAX_ID and trial_id["schema"]["minimum"] == 1
        (digest,) = spec["paths"]["/api/blobs/{digest}"]["get"]["parameters"]
        assert digest["schema"]["pattern"] == "^sha256:[0-9a-f]{64}$"
        answer = await client.get(f"/api/trials/{2**63}")
        assert answer.status_code == 422
        assert answer.json() == {
            "error": f"trial_id: Input should be less than or equal to {MAX_ID}"
        }
        answer = await client.get("/api/blobs/sha256:zz")
        assert answer.status_code == 422
        assert "digest: String should match pattern" in answer.json()["error"]


async def test_an_id_past_32_bits_is_a_422_on_either_database(tmp_path, database_url):
    """Trial 2^31 is a 422 naming the range in the API, on SQLite and on PostgreSQL (whose
    INTEGER id columns end at 2^31 - 1); the trial's page at such a URL is no page (404)."""
    service = Service(ServiceConfig(data=tmp_path / "data", database=database_url, workers=0))
    try:
        app = create_app(service, Site(), on_submit=lambda: None)
        async with httpx.AsyncClient(
            transport=httpx.ASGITransport(app=app), base_url="http://lab.test"
        ) as client:
            for path in (f"/api/trials/{2**31}", f"/api/trials?before={2**31}"):
                answer = await client.get(path)
                assert answer.status_code == 422, (path, answer.text)
            page = await client.get(f"/trials/{2**31}")
            assert page.status_code == 404 and f"no such page: /trials/{2**31}" in page.text
            assert (await client.get(f"/api/trials/{2**31 - 1}")).status_code == 404
    finally:
        service.index.close()
