"""Attacks on the API's edges (issue 24), against a real `labd serve`.

An anonymous client sends a 200 MiB body; integers past what the index holds and
malformed digests go into every parameter; the index's SQLite WAL is deleted while the
lab serves. Each must meet a clear 4xx or 503 at once, never a 500, a lab that reads
what it will refuse, or a loss nobody is told of.
"""

from __future__ import annotations

import itertools
import re
import select
import socket
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import httpx
import pytest

from labd import __version__
from scheduler.remote import PROTOCOL, PROTOCOL_HEADER, VERSION_HEADER
from tests.faults.conftest import Served
from tests.faults.slow import controller
from tests.helpers.githttp import GitRepo

pytestmark = pytest.mark.integration

MiB = 1 << 20
ATTACK = 200 * MiB  # the body an anonymous client offers
SMALL = 4 * MiB  # what may be sent before the refusal comes (the kernel's buffers hold some)


@dataclass
class Sent:
    """What a client that sends a large body got: the answer's status line and headers,
    and how many bytes of the body had been sent when it came."""

    head: str
    body: str
    sent: int
    peak_rss: int


def offer(
    served: Served,
    path: str,
    size: int,
    headers: dict[str, str],
    *,
    chunked: bool = False,
    chunk: int = MiB,
) -> Sent:
    """POST a JSON body of ``size`` bytes (a submission with a long repository URL) to
    ``path`` a chunk at a time (``chunked``: with no Content-Length), looking for an
    answer after each chunk; stop at the answer (or when the lab closes the connection)."""
    where = urlsplit(served.server)
    sock = socket.create_connection((where.hostname, where.port), timeout=30)
    lines = [f"POST {path} HTTP/1.1", f"Host: {where.netloc}", "Content-Type: application/json"]
    lines += ["Transfer-Encoding: chunked" if chunked else f"Content-Length: {size}"]
    lines += [f"{name}: {value}" for name, value in headers.items()]
    sock.sendall(("\r\n".join(lines) + "\r\n\r\n").encode())
    head, tail = b'{"task": "icreate-maze", "repository": "https://', b'"}'
    filler = b"x" * chunk
    sent, peak, answer = 0, served.rss(), b""
    try:
        while sent < size:
            readable, _, _ = select.select([sock], [], [], 0.02)
            if readable:
                break
            piece = filler[: min(chunk, size - sent)]
            if sent == 0:
                piece = head + piece[len(head) :]
            if sent + len(piece) == size:
                piece = piece[: -len(tail)] + tail
            if chunked:
                piece = b"%x\r\n%s\r\n" % (len(piece), piece)
            try:
                sock.sendall(piece)
            except (BrokenPipeError, ConnectionResetError):
                break
            sent += min(chunk, size - sent)
            peak = max(peak, served.rss())
        while not _whole(answer):
            try:
                more = sock.recv(65536)
            except ConnectionResetError:
                break
            if not more:
                break
            answer += more
    finally:
        sock.close()
    peak = max(peak, served.rss())
    head, _, body = answer.partition(b"\r\n\r\n")
    return Sent(head.decode("latin-1"), body.decode("utf-8", "replace"), sent, peak)


def _whole(answer: bytes) -> bool:
    """Whether ``answer`` holds a whole HTTP response (head, and a body of its length)."""
    head, found, body = answer.partition(b"\r\n\r\n")
    length = re.search(rb"(?im)^content-length: *(\d+)", head)
    return bool(found) and len(body) >= (int(length.group(1)) if length else 0)


@pytest.fixture
def served_lab(served: Callable[..., Served]) -> Served:
    served_lab = served("--no-robots", "--workers", "0", "--allow-local-repos")
    served_lab.start()
    served_lab.token = served_lab.add_user("alice")
    return served_lab


def test_an_anonymous_200_mib_body_is_refused_before_it_is_read(served_lab: Served):
    """A write with no token is answered 401 after at most a few MiB of its 200 MiB body
    were sent, and the server's memory does not grow with the body."""
    before = served_lab.rss()
    got = offer(served_lab, "/api/trials", ATTACK, {})
    grew = (got.peak_rss - before) / MiB
    print(f"\nanonymous 200 MiB body: answered after {got.sent / MiB:.0f} MiB sent;"
          f" RSS {before / MiB:.0f} MiB, peak +{grew:.1f} MiB; {got.head.splitlines()[:1]}")  # fmt: skip
    assert got.head.startswith("HTTP/1.1 401"), got.head
    assert got.sent <= SMALL, f"the 401 came after {got.sent / MiB:.0f} MiB of the body"
    assert grew < 32, f"the server grew by {grew:.0f} MiB while refusing the body"


@pytest.mark.parametrize("chunked", [False, True], ids=["content-length", "chunked"])
def test_a_writers_body_over_its_routes_limit_is_refused_with_413(
    served_lab: Served, chunked: bool
):
    """A writer's 200 MiB JSON body is answered 413 naming the 1 MiB limit: from its
    Content-Length before it is read, or as soon as a chunked stream passes the limit."""
    before = served_lab.rss()
    got = offer(
        served_lab,
        "/api/trials",
        ATTACK,
        {"Authorization": f"Bearer {served_lab.token}"},
        chunked=chunked,
    )
    grew = (got.peak_rss - before) / MiB
    print(f"\nwriter's 200 MiB body ({'chunked' if chunked else 'content-length'}): answered"
          f" after {got.sent / MiB:.0f} MiB sent; RSS peak +{grew:.1f} MiB")  # fmt: skip
    assert got.head.startswith("HTTP/1.1 413"), got.head
    assert "1 MiB" in got.body, got.body
    assert got.sent <= SMALL, f"the 413 came after {got.sent / MiB:.0f} MiB of the body"
    assert grew < 32, f"the server grew by {grew:.0f} MiB while refusing the body"


# -- integers past the index's range, digests that are not ------------------------------

HUGE = (2**70, 2**63, -(2**70))  # past SQLite's 64 bits, past them by one, far below


def _schema(spec: dict[str, Any], schema: dict[str, Any]) -> dict[str, Any]:
    if "$ref" in schema:
        return _schema(spec, spec["components"]["schemas"][schema["$ref"].split("/")[-1]])
    return schema


def _sample(spec: dict[str, Any], schema: dict[str, Any], ids: int) -> Any:
    """A valid-looking value of ``schema`` (``ids`` for every integer), so that only the
    field under attack is wrong."""
    schema = _schema(spec, schema)
    if "anyOf" in schema:
        return _sample(spec, next(s for s in schema["anyOf"] if s.get("type") != "null"), ids)
    kind = schema.get("type")
    if kind == "integer":
        return ids
    if kind == "number":
        return 1.0
    if kind == "boolean":
        return False
    if kind == "array":
        return [_sample(spec, schema["items"], ids)]
    if kind == "string":
        if "enum" in schema:
            return schema["enum"][0]
        if schema.get("pattern", "").startswith("^sha256"):
            return "sha256:" + "0" * 64
        return "2030-01-01T00:00:00Z" if schema.get("format") == "date-time" else "x"
    props = schema.get("properties", {})
    return {name: _sample(spec, s, ids) for name, s in props.items()}


def _integers(spec: dict[str, Any], schema: dict[str, Any], at: tuple[Any, ...] = ()) -> list:
    """Where ``schema`` holds an integer: a path of keys (0 for a list's item)."""
    schema = _schema(spec, schema)
    found = [at] if schema.get("type") == "integer" else []
    for option in schema.get("anyOf", []):
        found += _integers(spec, option, at)
    if schema.get("type") == "array":
        found += _integers(spec, schema["items"], (*at, 0))
    for name, inner in schema.get("properties", {}).items():
        found += _integers(spec, inner, (*at, name))
    return found


def _put(body: Any, at: tuple[Any, ...], value: int) -> Any:
    if not at:
        return value
    inner = body
    for key in at[:-1]:
        inner = inner[key]
    inner[at[-1]] = value
    return body


def attacks(spec: dict[str, Any], ids: int) -> Iterator[tuple[str, str, dict, Any, str]]:
    """Every request of the OpenAPI document with one integer (a parameter, or a field of
    its JSON body) set to each of ``HUGE``: method, path, query, body, what is attacked."""
    for template, operations in spec["paths"].items():
        for method, operation in operations.items():
            params = operation.get("parameters", [])
            body = operation.get("requestBody", {}).get("content", {}).get("application/json")
            targets: list[tuple[str, Any]] = [
                ("param", p["name"]) for p in params if _integers(spec, p["schema"])
            ]
            if body:
                targets += [("body", at) for at in _integers(spec, body["schema"])]
            for (where, name), huge in itertools.product(targets, HUGE):
                path, query = template, {}
                for p in params:
                    value = huge if (where, name) == ("param", p["name"]) else None
                    if p["in"] == "path":
                        value = value if value is not None else _sample(spec, p["schema"], ids)
                        path = path.replace("{" + p["name"] + "}", str(value))
                    elif p["in"] == "query" and (value is not None or p.get("required")):
                        query[p["name"]] = (
                            value if value is not None else _sample(spec, p["schema"], ids)
                        )
                sent = _sample(spec, body["schema"], ids) if body else None
                if where == "body":
                    sent = _put(sent, name, huge)
                yield method.upper(), path, query, sent, f"{where} {name}={huge}"


def test_no_integer_or_digest_a_client_sends_answers_500(
    served_lab: Served, tmp_path: Path
) -> None:
    """Every integer of every API route (parameters and JSON fields, from /openapi.json),
    set past the index's range, and a malformed blob digest are answered with a 4xx the
    OpenAPI document declares, ``{"error": ...}``; so are the pages' ids and a lab.toml
    pinning trial 2^63."""
    worker = served_lab.add_user("robot", "--worker")
    trial = served_lab.submit(GitRepo.create(tmp_path / "r", controller(3)).path)
    headers = {
        "Authorization": f"Bearer {worker}",
        PROTOCOL_HEADER: str(PROTOCOL),
        VERSION_HEADER: __version__,
    }
    with httpx.Client(base_url=served_lab.server, headers=headers, timeout=60) as client:
        claimed = client.post("/api/workers/claim", json={"worker": "w1"})
        assert claimed.status_code == 200 and claimed.json()["id"] == trial["id"]
        spec = client.get("/openapi.json").json()
        tried, wrong = 0, []
        for method, path, query, body, what in attacks(spec, trial["id"]):
            tried += 1
            answer = _ask(client, wrong, method, path, what, params=query, json=body)
            if answer is not None and not _declared_4xx(spec, method, path, answer):
                wrong.append(f"{method} {path} {what}: {answer.status_code} {answer.text[:160]}")
        for digest in ("not-hex", "sha256:zz", "sha256:" + "A" * 64, "sha256:" + "0" * 65):
            for method in ("GET", "PUT"):
                tried += 1
                path = f"/api/blobs/{digest}"
                answer = _ask(client, wrong, method, path, "", content=b"x")
                if answer is not None and not _declared_4xx(spec, method, path, answer):
                    wrong.append(f"{method} {path}: {answer.status_code} {answer.text}")
        pages = [f"/trials/{2**70}", f"/trials?before={2**63}", f"/trials?page={2**70}"]
        for path in pages:
            tried += 1
            answer = _ask(client, wrong, "GET", path, "")
            if answer is not None and answer.status_code >= 500:
                wrong.append(f"GET {path}: {answer.status_code} {answer.text[:160]}")
        print(f"\n{tried} requests with an integer past the index's range or a bad digest")
        assert wrong == [], "\n".join(wrong)
    pins = controller(3)
    pins["lab.toml"] += f"\n[data]\ntrials = [{2**63}]\n"
    answer = httpx.post(
        f"{served_lab.server}/api/trials",
        json={
            "repository": str(GitRepo.create(tmp_path / "pins", pins).path),
            "task": "icreate-maze",
        },
        headers={"Authorization": f"Bearer {served_lab.token}"},
        timeout=60,
    )
    assert answer.status_code == 422, answer.text
    assert "is no trial id (trial ids are 1 to 2147483647)" in answer.json()["error"]


def _ask(
    client: httpx.Client, wrong: list[str], method: str, path: str, what: str, **sent: Any
) -> httpx.Response | None:
    """The answer to one request; None, and a line in ``wrong``, if none came."""
    try:
        return client.request(method, path, **sent)
    except httpx.TransportError as err:
        wrong.append(f"{method} {path} {what}: no answer ({err!r})")
        return None


def _declared_4xx(spec: dict[str, Any], method: str, path: str, answer: httpx.Response) -> bool:
    """Whether ``answer`` is a 4xx with ``{"error": ...}`` that the OpenAPI document
    declares for the route of ``path``."""
    if not 400 <= answer.status_code < 500 or set(answer.json()) != {"error"}:
        return False
    for template, operations in spec["paths"].items():
        if re.fullmatch(re.sub(r"\{[^}]+\}", "[^/]+", template), path):
            declared = operations.get(method.lower(), {}).get("responses", {})
            return str(answer.status_code) in declared
    return answer.status_code == 404


# -- the index's WAL deleted while the lab serves ---------------------------------------


def test_a_deleted_wal_is_detected_and_writes_are_refused(
    served_lab: Served, tmp_path: Path
) -> None:
    """Once the index's SQLite WAL is deleted under a serving lab, writes are refused with
    503 saying what happened and what to do, /readyz answers the same, the log says so,
    and after a crash the restarted lab still has every trial and user written before."""
    repo = GitRepo.create(tmp_path / "r", controller(3)).path
    filed = [served_lab.submit(repo)["id"] for _ in range(3)]
    assert httpx.get(f"{served_lab.server}/readyz", timeout=30).status_code == 200
    wal = served_lab.data / "index.sqlite-wal"
    assert wal.exists()
    wal.unlink()
    answer = httpx.post(
        f"{served_lab.server}/api/trials",
        json={"repository": str(repo), "task": "icreate-maze"},
        headers={"Authorization": f"Bearer {served_lab.token}"},
        timeout=60,
    )
    ready = httpx.get(f"{served_lab.server}/readyz", timeout=30)
    print(f"\nafter the WAL was deleted: submit {answer.status_code} {answer.text[:300]};"
          f" /readyz {ready.status_code}")  # fmt: skip
    assert answer.status_code == 503, answer.text
    refusal = answer.json()["error"]
    assert f"{wal} was deleted or replaced" in refusal
    assert "nothing is lost" in refusal and "restart labd serve" in refusal
    assert ready.status_code == 503 and ready.json() == {"error": f"not ready: index: {refusal}"}
    assert refusal in served_lab.log
    served_lab.kill()  # a crash: the WAL's content is wherever the lab put it
    served_lab.start()
    kept = [t["id"] for t in served_lab.get("/api/trials")["trials"]]
    assert sorted(kept) == filed
    assert served_lab.submit(repo)["id"] == filed[-1] + 1  # alice and her token are still there
