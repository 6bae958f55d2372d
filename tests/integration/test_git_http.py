"""The hosted repositories over git's smart HTTP, through a whole lab's HTTP port.

A real lab (its app with every middleware, served by uvicorn on 127.0.0.1 and a free
port) hosts repositories committed through ``service.hosted``; a real ``git`` clones
and fetches them (protocol v2 and v0), is refused a push, and finds no repository
that is not there; raw requests try to climb out of ``DATA/git`` and to send more than
a fetch may.
"""

from __future__ import annotations

import contextlib
import http.client
import os
import random
import re
import shutil
import socket
import subprocess
from collections.abc import Iterator
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import psutil
import pytest
from starlette.routing import Mount

from labd.api.git import MAX_UPLOAD, GitHttp, GitLimits
from labd.hosted import HostedRepos, git_environment
from tests.helpers.labs import ServerThread, lab_config, running

pytestmark = pytest.mark.integration

WHEN = 1_700_000_000
FILES = {
    "lab.toml": b'[controller]\ncommand = ["node", "main.mjs"]\ntask = "icreate-maze"\n',
    "package.json": b'{"type": "module"}\n',
    "main.mjs": b"console.log('tick');\n",
    "src/lib/util.mjs": b"export const x = 1;\n",
}
WAIT = 30.0


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServerThread]:
    """A lab with the archive and no robot; ``alice/robot`` hosted, one commit in it;
    a repository outside DATA/git (``DATA/secret.git``) to be kept out of reach."""
    data = tmp_path_factory.mktemp("git-http") / "data"
    with running(lab_config(data, ())) as server:
        hosted = server.lab.service.hosted
        hosted.commit("alice", "robot", FILES, "first", author="alice", when=WHEN)
        outside = HostedRepos(data / "outside")
        outside.commit("mallory", "secret", {"key": b"s3cret"}, "m", author="mallory", when=WHEN)
        shutil.move(outside.path("mallory", "secret"), data / "secret.git")
        yield server


@pytest.fixture
def hosted(server: ServerThread) -> HostedRepos:
    return server.lab.service.hosted


@pytest.fixture
def backends(server: ServerThread) -> GitHttp:
    """The lab's mounted git app (its limits may be changed by a test, and are reset)."""
    mount = next(r for r in server.lab.app.routes if isinstance(r, Mount) and r.path == "/git")
    app = mount.app
    assert isinstance(app, GitHttp)
    yield app
    app.limits = GitLimits()


def url(server: ServerThread, path: str) -> str:
    return server.http_url(f"/git/{path}")


def git(*args: str, cwd: Path | None = None, check: bool = True, **env: str) -> Any:
    """Run a git client, in a clean environment (no proxy, no user's configuration)."""
    return subprocess.run(
        ["git", *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        check=check,
        timeout=WAIT,
        env=git_environment(env),
    )


def raw(server: ServerThread, method: str, path: str, body: bytes = b"", **headers: str) -> Any:
    """One request with ``path`` sent exactly as written (no client normalizes it)."""
    where = urlsplit(server.http_url())
    connection = http.client.HTTPConnection(where.hostname or "", where.port, timeout=WAIT)
    try:
        connection.request(method, path, body=body or None, headers=headers)
        response = connection.getresponse()
        response.text = response.read().decode("utf-8", "replace")
        return response
    finally:
        connection.close()


@pytest.mark.parametrize("version", ["2", "0"])
def test_a_clone_gives_the_committed_files_and_commit(server, hosted, tmp_path, version):
    """``git clone`` over HTTP, with protocol v2 or v0, checks out the hosted commit:
    the same id, the same files, nested ones included."""
    sha = hosted.head("alice", "robot")
    work = tmp_path / "clone"
    done = git(
        "-c", f"protocol.version={version}", "clone", url(server, "alice/robot.git"), str(work),
        GIT_TRACE_PACKET="1",
    )  # fmt: skip
    spoke_v2 = "git< version 2" in done.stderr
    assert spoke_v2 == (version == "2"), done.stderr[-2000:]
    assert git("rev-parse", "HEAD", cwd=work).stdout.strip() == sha
    assert git("rev-parse", "--abbrev-ref", "HEAD", cwd=work).stdout.strip() == "main"
    for path, data in FILES.items():
        assert (work / path).read_bytes() == data


def test_a_fetch_after_another_commit_gets_it(server, hosted, tmp_path):
    """A clone fetches the next commit the lab makes, over v2 and v0."""
    first = hosted.commit("alice", "fetched", FILES, "one", author="alice", when=WHEN)
    work = tmp_path / "clone"
    git("clone", url(server, "alice/fetched.git"), str(work))
    second = hosted.commit(
        "alice", "fetched", {**FILES, "main.mjs": b"go();\n"}, "two", author="alice", when=WHEN + 1
    )
    git("-c", "protocol.version=0", "fetch", "origin", cwd=work)
    assert git("rev-parse", "origin/main", cwd=work).stdout.strip() == second
    assert git("rev-parse", "origin/main^", cwd=work).stdout.strip() == first
    third = hosted.commit("alice", "fetched", FILES, "three", author="alice", when=WHEN + 2)
    git("-c", "protocol.version=2", "pull", "--ff-only", cwd=work)
    assert git("rev-parse", "HEAD", cwd=work).stdout.strip() == third


def test_a_push_is_refused_and_the_repository_is_unchanged(server, hosted, tmp_path):
    """``git push`` is answered 403, git shows the lab's one line, and main stays."""
    before = hosted.head("alice", "robot")
    work = tmp_path / "clone"
    git("clone", url(server, "alice/robot.git"), str(work))
    (work / "main.mjs").write_text("pwned();\n")
    git("-c", "user.name=m", "-c", "user.email=m@x", "commit", "-qam", "mine", cwd=work)
    pushed = git("push", "origin", "HEAD:main", cwd=work, check=False)
    assert pushed.returncode != 0
    assert "remote: the playground's repositories are written only through the playground" in (
        pushed.stderr
    ), pushed.stderr
    assert "403" in pushed.stderr
    assert hosted.head("alice", "robot") == before
    for path in ("alice/robot.git/info/refs?service=git-receive-pack",):
        assert raw(server, "GET", f"/git/{path}").status == 403
    posted = raw(
        server, "POST", "/git/alice/robot.git/git-receive-pack", b"0000",
        **{"Content-Type": "application/x-git-receive-pack-request"},
    )  # fmt: skip
    assert posted.status == 403
    assert posted.getheader("Content-Type").startswith("text/plain")


def test_an_unknown_repository_is_404(server):
    """``git ls-remote`` of a repository the lab does not host fails with "not found",
    after the lab's own words."""
    listed = git("ls-remote", url(server, "alice/nothing.git"), check=False)
    assert listed.returncode != 0
    assert "remote: repository alice/nothing: is not on this lab" in listed.stderr
    assert "not found" in listed.stderr
    answer = raw(server, "GET", "/git/nobody/robot.git/info/refs?service=git-upload-pack")
    assert answer.status == 404
    assert answer.text == "repository nobody/robot: is not on this lab\n"


OUTSIDE = [
    "/git/../secret.git/info/refs?service=git-upload-pack",
    "/git/alice/../../secret.git/info/refs?service=git-upload-pack",
    "/git/alice/..%2f..%2fsecret.git/info/refs?service=git-upload-pack",
    "/git/u/..%2f..%2fkeys.git/info/refs?service=git-upload-pack",
    "/git/%2e%2e/secret.git/info/refs?service=git-upload-pack",
    "/git/alice/%2e%2e%2fsecret.git/info/refs?service=git-upload-pack",
    "/git/alice/robot.git/../../../secret.git/info/refs?service=git-upload-pack",
    "/git//secret.git/info/refs?service=git-upload-pack",
    "/git/alice/robot%20x.git/info/refs?service=git-upload-pack",
    "/git/al%20ice/robot.git/info/refs?service=git-upload-pack",
    "/git/alice/robot.git.git/info/refs?service=git-upload-pack",
    "/git/alice/evil.git/info/refs?service=git-upload-pack",  # a symbolic link out
    "/git/alice/robot.git/HEAD",  # the dumb protocol's files are not served
    "/git/alice/robot.git/config",
    "/git/alice/robot.git/objects/info/packs",
    "/git/alice/robot.git/info/refs",
    "/git/alice/robot.git/info/refs?service=git-upload-archive",
]


@pytest.mark.parametrize("path", OUTSIDE)
def test_no_path_reaches_outside_the_hosted_repositories(server, hosted, path):
    """Climbing out of DATA/git (``..``, encoded or not, a symbolic link placed in it),
    malformed names and files of a repository are never answered 200, and never with
    what lies outside (a repository at DATA/secret.git)."""
    link = hosted.root / "alice" / "evil.git"
    if not link.exists():
        link.symlink_to(hosted.root.parent / "secret.git")
    secret = (hosted.root.parent / "secret.git" / "refs" / "heads" / "main").read_text().strip()
    answer = raw(server, "GET", path)
    assert answer.status in (400, 404), (answer.status, answer.text)
    assert secret not in answer.text
    assert "s3cret" not in answer.text
    assert answer.getheader("Content-Type").startswith(("text/plain", "application/json"))


def test_a_post_over_the_body_limit_is_413(server, backends):
    """A fetch's body over 16 MiB is refused with 413 from its Content-Length, before
    any backend runs."""
    sock = _post(server, f"Content-Length: {MAX_UPLOAD + 1}")
    try:
        with contextlib.suppress(BrokenPipeError, ConnectionResetError):
            sock.sendall(b"0" * (MAX_UPLOAD + 1))
        answer = _read_answer(sock)
    finally:
        sock.close()
    assert answer.startswith(b"HTTP/1.1 413"), answer[:200]
    assert b"(16 MiB)" in answer
    assert backends.running == 0


def test_a_chunked_post_over_the_body_limit_is_413_and_its_backend_ends(server, backends):
    """Without a Content-Length, the body streams to the backend until it passes 16 MiB:
    then the answer is 413 in words git shows, and the backend is gone."""
    sock = _post(server)
    sent, answer = 0, b""
    try:
        piece = b"0" * (1024 * 1024)
        while sent <= MAX_UPLOAD + len(piece):
            try:
                sock.sendall(b"%x\r\n%s\r\n" % (len(piece), piece))
            except (BrokenPipeError, ConnectionResetError):
                break
            sent += len(piece)
        answer = _read_answer(sock)
    finally:
        sock.close()
    assert answer.startswith(b"HTTP/1.1 413"), answer[:200]
    assert b"content-type: text/plain" in answer.lower()
    assert b"the request's body is larger than this route takes (16 MiB)" in answer
    server.wait_until(lambda: backends.running == 0)
    assert _backends() == []


def test_a_client_that_goes_away_has_its_backend_killed(server, backends):
    """A client that sends half a fetch and closes the connection leaves no backend."""
    sock = _post(server)
    sock.sendall(b"4\r\n0000\r\n")
    server.wait_until(lambda: len(_backends()) == 1)
    sock.close()
    server.wait_until(lambda: backends.running == 0)  # after its backend was reaped
    assert _backends() == []


def test_a_backend_past_its_time_is_killed_and_answered_504(server, backends):
    """A fetch whose body never ends is cut at the time limit: 504, backend killed."""
    backends.limits = GitLimits(timeout=1.0)
    sock = _post(server)
    try:
        sock.sendall(b"4\r\n0000\r\n")
        answer = _read_answer(sock)
    finally:
        sock.close()
    assert answer.startswith(b"HTTP/1.1 504"), answer[:200]
    assert b"git took longer than this lab's limit of 1 s" in answer
    server.wait_until(lambda: backends.running == 0)
    assert _backends() == []


def test_past_the_backends_it_takes_the_lab_answers_503(server, backends):
    """With all its backends busy, the lab answers 503 with Retry-After."""
    backends.limits = GitLimits(backends=0, retry_after=7)
    answer = raw(server, "GET", "/git/alice/robot.git/info/refs?service=git-upload-pack")
    assert answer.status == 503
    assert answer.getheader("Retry-After") == "7"
    assert "try again in 7 s" in answer.text


def _post(server: ServerThread, length: str = "Transfer-Encoding: chunked") -> socket.socket:
    """A socket that has sent the head of a fetch from alice/robot (chunked, unless
    ``length`` says otherwise), and none of its body."""
    where = urlsplit(server.http_url())
    sock = socket.create_connection((where.hostname, where.port), timeout=WAIT)
    sock.sendall(
        b"POST /git/alice/robot.git/git-upload-pack HTTP/1.1\r\nHost: lab\r\n"
        b"Content-Type: application/x-git-upload-pack-request\r\n%s\r\n\r\n" % length.encode()
    )
    return sock


def _read_answer(sock: socket.socket) -> bytes:
    """What the server answers, until it closes or the body's length is in."""
    answer = b""
    while True:
        try:
            more = sock.recv(65536)
        except ConnectionResetError:
            break
        if not more:
            break
        answer += more
        head, found, body = answer.partition(b"\r\n\r\n")
        length = re.search(rb"(?im)^content-length: *(\d+)", head)
        if found and length and len(body) >= int(length.group(1)):
            break
    return answer


def _backends() -> list[psutil.Process]:
    """This process's ``git http-backend`` children (the lab runs in this process)."""
    found = []
    for child in psutil.Process(os.getpid()).children(recursive=True):
        try:
            if child.cmdline()[:2] == ["git", "http-backend"] and child.status() != "zombie":
                found.append(child)
        except psutil.NoSuchProcess:
            continue
    return found


def test_a_large_repository_and_a_gzipped_negotiation(server, hosted, tmp_path):
    """A repository of several MiB clones whole (the pack streams in many chunks), and a
    fetch whose negotiation is large enough for git to gzip its request gets the new
    commit (the backend is told the request's encoding)."""
    noise = random.Random(7).randbytes(3 * 1024 * 1024)  # does not compress
    hosted.commit("alice", "large", {**FILES, "noise.bin": noise}, "m", author="alice", when=WHEN)
    work = tmp_path / "clone"
    git("clone", url(server, "alice/large.git"), str(work))
    assert (work / "noise.bin").read_bytes() == noise
    for i in range(64):  # local commits: each is a "have" the fetch offers
        git("-c", "user.name=m", "-c", "user.email=m@x", "commit", "-q", "--allow-empty",
            "-m", f"local {i}", cwd=work)  # fmt: skip
    new = hosted.commit("alice", "large", FILES, "smaller", author="alice", when=WHEN + 1)
    fetched = git("-c", "protocol.version=2", "fetch", "origin", cwd=work, GIT_TRACE_CURL="1")
    assert "Content-Encoding: gzip" in fetched.stderr
    assert git("rev-parse", "origin/main", cwd=work).stdout.strip() == new
