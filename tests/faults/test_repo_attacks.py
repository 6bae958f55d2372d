"""Attacks through repositories and submissions (issue 24), on a real `labd serve`.

- a commit of a repository well within ``--max-repo-mb`` that expands to 1 GiB (one file
  of zeros, or 1,024 paths sharing one blob) must be refused before anything is expanded,
  in memory or on disk;
- submissions to a git server that never answers must not hold the threads that answer
  anonymous reads;
- local paths and ``file://`` URLs are refused unless the operator allows them, without
  telling whether a folder exists, and never reach the lab's own folders;
- ``[data] trials = [2^63]`` in lab.toml is a 4xx, not a 500.
"""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import os
import socket
import statistics
import threading
import time
import zlib
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import httpx
import psutil
import pytest

from tests.faults.conftest import Served
from tests.helpers.githttp import GitRepo
from tests.helpers.timing import SECOND

pytestmark = [pytest.mark.integration, pytest.mark.rates]

MiB = 1024 * 1024
GiB = 1024 * MiB
TOML = '[controller]\ncommand = ["python", "c.py"]\ntask = "icreate-maze"\n'
FILES = {"lab.toml": TOML, "c.py": "print('hello')\n"}


def post(lab: Served, repository: str, timeout: float = 120) -> httpx.Response:
    return httpx.post(
        f"{lab.server}/api/trials",
        json={"repository": repository, "task": "icreate-maze"},
        headers={"Authorization": f"Bearer {lab.token}"},
        timeout=timeout,
    )


# -- 1. a commit that expands past the limit ----------------------------------------------


def zeros(repo: GitRepo, size: int) -> str:
    """A blob of ``size`` zero bytes, written into ``repo`` as `git add` would (a loose,
    zlib-compressed object); its id. Written here, not from a file: nothing of its size
    touches the disk."""
    header = f"blob {size}\0".encode()
    digest = hashlib.sha1(header)  # git names objects by their SHA-1
    packer = zlib.compressobj(1)
    chunk = bytes(MiB)
    parts = [packer.compress(header)]
    for _ in range(size // MiB):
        digest.update(chunk)
        parts.append(packer.compress(chunk))
    parts.append(packer.flush())
    name = digest.hexdigest()
    folder = repo.path / ".git" / "objects" / name[:2]
    folder.mkdir(parents=True, exist_ok=True)
    (folder / name[2:]).write_bytes(b"".join(parts))
    return name


def one_big_file(path: Path) -> GitRepo:
    """lab.toml, and a file of 1 GiB of zeros (about 4.5 MiB in git)."""
    repo = GitRepo.create(path, FILES)
    blob = zeros(repo, GiB)
    repo.git("update-index", "--add", "--cacheinfo", f"100644,{blob},zeros.bin")
    repo.git("commit", "-q", "-m", "1 GiB of zeros")
    return repo


def many_copies(path: Path) -> GitRepo:
    """lab.toml, and 1,024 files that share one blob of 1 MiB of zeros (1 GiB checked
    out, a few KiB in git)."""
    repo = GitRepo.create(path, FILES)
    blob = zeros(repo, MiB)
    lines = "".join(f"100644 {blob}\tcopies/{n:04}.bin\n" for n in range(1024))
    repo.git("update-index", "--index-info", input=lines)
    repo.git("commit", "-q", "-m", "1,024 copies of 1 MiB")
    return repo


def tree_bomb(path: Path) -> GitRepo:
    """lab.toml, and a folder that names one folder 1,000 times, which names one 1-byte
    file 1,000 times: a million files checked out, a few KiB in git."""
    repo = GitRepo.create(path, FILES)
    blob = repo.git("hash-object", "-w", "--stdin", input="x")
    inner = repo.git("mktree", input="".join(f"100644 blob {blob}\tf{n}\n" for n in range(1000)))
    outer = repo.git("mktree", input="".join(f"040000 tree {inner}\td{n}\n" for n in range(1000)))
    repo.git("read-tree", "--prefix=bomb/", outer)
    repo.git("commit", "-q", "-m", "a million files")
    return repo


def size_of(folders: list[Path]) -> int:
    total = 0
    for folder in folders:
        for root, _, names in os.walk(folder):
            for name in names:
                with contextlib.suppress(OSError):
                    total += os.lstat(os.path.join(root, name)).st_size
    return total


class Peak:
    """The most the server's memory (RSS) and the files under ``folders`` grew while the
    block ran, sampled every 20 ms in a thread."""

    def __init__(self, pid: int, folders: list[Path]) -> None:
        self.process = psutil.Process(pid)
        self.folders = folders
        self.rss = self.disk = 0
        self._done = threading.Event()

    def _sample(self) -> tuple[int, int]:
        return int(self.process.memory_info().rss), size_of(self.folders)

    def __enter__(self) -> Peak:
        self._base = self._sample()
        self._thread = threading.Thread(target=self._watch, daemon=True)
        self._thread.start()
        return self

    def _watch(self) -> None:
        while not self._done.wait(0.02):
            rss, disk = self._sample()
            self.rss = max(self.rss, rss - self._base[0])
            self.disk = max(self.disk, disk - self._base[1])

    def __exit__(self, *exc: object) -> None:
        self._done.set()
        self._thread.join()
        rss, disk = self._sample()
        self.rss = max(self.rss, rss - self._base[0])
        self.disk = max(self.disk, disk - self._base[1])


@pytest.mark.timeout(240)
def test_a_commit_that_expands_past_the_limit_is_refused_before_it_is_expanded(
    make_bare_lab: Callable[..., Served], tmp_path: Path
) -> None:
    """A commit within --max-repo-mb 5 whose files add up to 1 GiB (or that holds a
    million files) is refused at submit time with a 413 naming its size and the limit,
    and neither the server's memory nor its disk grows by more than the compressed
    repository."""
    temporary = tmp_path / "tmp"  # where the server's temporary files go
    temporary.mkdir()
    served = make_bare_lab(
        "--max-repo-mb", "5", "--allow-local-repos", env={"TMPDIR": str(temporary)}
    )
    watched = [temporary, served.data, served.cache]
    for make in (one_big_file, many_copies, tree_bomb):
        repo = make(tmp_path / make.__name__)
        with Peak(served.pid, watched) as peak:
            started = time.monotonic()
            answer = post(served, str(repo.path))
            took = time.monotonic() - started
        print(
            f"{make.__name__}: {answer.status_code} in {took:.1f} s; server RSS +"
            f"{peak.rss / MiB:.0f} MiB, disk +{peak.disk / MiB:.1f} MiB at most"
        )
        assert answer.status_code == 413, answer.text
        error = answer.json()["error"]
        if make is tree_bomb:
            assert "checks out to more than this lab's limit of 100,000 files" in error, error
        else:
            limit = "checks out to more than this lab's limit of 512.0 MiB (--max-checkout-mb)"
            assert limit in error, error
        if make is one_big_file:
            assert "(at least 1024.0 MiB)" in error, error
        assert peak.rss < 100 * MiB, f"the server's memory grew by {peak.rss / MiB:.0f} MiB"
        assert peak.disk < 16 * MiB, f"the disk grew by {peak.disk / MiB:.1f} MiB"
    assert served.get("/api/trials")["trials"] == []


# -- 2. submissions to a git server that never answers -------------------------------------


@contextlib.contextmanager
def silent_git_server() -> Iterator[str]:
    """A git:// URL whose server takes connections (the kernel completes them) and never
    answers a byte."""
    listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    listener.bind(("127.0.0.1", 0))
    listener.listen(256)
    try:
        yield f"git://127.0.0.1:{listener.getsockname()[1]}/robot.git"
    finally:
        listener.close()


SUBMISSIONS = 80  # past the pool's 8 at once and 64 waiting
READS = ("/api/trials", "/trials", "/api/status", "/")
RESOLVE = 3  # seconds: the lab's resolve timeout in this test (default 60 s)


async def crowd(
    served: Served, url: str
) -> tuple[list[httpx.Response | BaseException], list[tuple[float, float]], list[float]]:
    """SUBMISSIONS submissions of ``url`` at once; meanwhile anonymous reads, one after
    another until every submission has its answer (or gave up waiting for one). The
    answers; when each read began and how long it took; when each submission's answer
    came."""
    headers = {"Authorization": f"Bearer {served.token}"}
    reads: list[tuple[float, float]] = []
    answered: dict[int, float] = {}
    async with httpx.AsyncClient(base_url=served.server, timeout=60 * SECOND) as client:

        async def submit(n: int) -> httpx.Response:
            body = {"repository": url, "task": "icreate-maze", "seed": n}
            try:
                return await client.post("/api/trials", json=body, headers=headers)
            finally:
                answered[n] = time.monotonic()

        submitting = asyncio.gather(
            *(submit(n) for n in range(SUBMISSIONS)), return_exceptions=True
        )
        async with httpx.AsyncClient(base_url=served.server, timeout=30 * SECOND) as reader:
            n = 0
            while not submitting.done() and len(reads) < 5000:
                started = time.monotonic()
                answer = await reader.get(READS[n % len(READS)])
                assert answer.status_code == 200, answer.text
                reads.append((started, time.monotonic() - started))
                n += 1
        answers = await submitting
    return answers, reads, [answered[n] for n in range(SUBMISSIONS)]


@pytest.mark.timeout(180 * SECOND)
def test_submissions_to_a_silent_git_server_leave_anonymous_reads_quick(
    make_bare_lab: Callable[..., Served],
) -> None:
    """80 submissions of a repository whose server never answers: anonymous reads are
    answered (each page, again and again) while the submissions the lab took in hand
    wait, and each of those ends at the resolution deadline, the rest told the lab is
    busy past the 72 it takes in hand."""
    served = make_bare_lab("--resolve-timeout", str(RESOLVE), "--allow-private-hosts")  # loopback
    with silent_git_server() as url:
        started = time.monotonic()
        answers, reads, answered = asyncio.run(crowd(served, url))
        took = time.monotonic() - started
    kinds = [a.status_code if isinstance(a, httpx.Response) else type(a).__name__ for a in answers]
    statuses = {kind: kinds.count(kind) for kind in set(kinds)}
    ends = sorted(
        at
        for at, answer in zip(answered, answers, strict=True)
        if isinstance(answer, httpx.Response) and answer.status_code == 422
    )
    # reads over while every submission in hand still waited (before the first deadline)
    while_held = sum(began + seconds < ends[0] for began, seconds in reads) if ends else 0
    latencies = sorted(seconds for _, seconds in reads)
    p99 = latencies[min(len(latencies) - 1, int(len(latencies) * 0.99))]
    print(
        f"{SUBMISSIONS} hanging submissions answered in {took:.1f} s ({statuses});"
        f" {len(latencies)} reads meanwhile, {while_held} before the first deadline:"
        f" p50 {statistics.median(latencies) * 1000:.0f} ms, p99 {p99 * 1000:.0f} ms,"
        f" max {latencies[-1] * 1000:.0f} ms"
    )
    assert while_held >= 2 * len(READS), f"{while_held} reads answered while submissions waited"
    for answer in answers:
        assert isinstance(answer, httpx.Response), f"a submission got no answer: {answer!r}"
        if answer.status_code == 503:
            assert "try again" in answer.json()["error"] and answer.headers["Retry-After"]
        else:
            assert answer.status_code == 422, answer.text
            assert f"took longer than this lab's limit of {RESOLVE} s" in answer.json()["error"]
    assert statuses.get(422, 0) >= 72 and statuses.get(503, 0) > 0, statuses
    assert served.get("/api/trials")["trials"] == []


# -- 3. local paths -------------------------------------------------------------------------


def test_local_paths_are_refused_unless_the_operator_allows_them(
    make_bare_lab: Callable[..., Served], tmp_path: Path
) -> None:
    """Without --allow-local-repos, every local path and file:// URL (a repository, a
    folder, nothing at all) gets the same 422 naming the flag, so nothing is learnt of
    the host's folders, and nothing is queued."""
    repo = GitRepo.create(tmp_path / "robot", FILES)
    served = make_bare_lab()
    probes = [
        str(repo.path),
        repo.url,
        str(tmp_path / "no-such-folder"),
        f"file://{tmp_path / 'no-such-folder'}",
        "/etc",
        "../../../../etc",
        str(served.data),
        str(served.cache / "mirrors"),
    ]
    seen = set()
    for probe in probes:
        answer = post(served, probe)
        assert answer.status_code == 422, (probe, answer.text)
        error = answer.json()["error"]
        assert "--allow-local-repos" in error, error
        seen.add(error.replace(probe, "PATH", 1))
    assert len(seen) == 1, seen  # the same words whatever is (or is not) there
    assert served.get("/api/trials")["trials"] == []


def test_allowed_local_paths_never_reach_the_labs_own_folders(
    make_bare_lab: Callable[..., Served], tmp_path: Path
) -> None:
    """With --allow-local-repos, a repository of the host is taken, but the lab's own
    folders (its git mirrors and cache, its blobs, keys and work) and what lies below
    them are refused with a 422, by whatever path."""
    repo = GitRepo.create(tmp_path / "robot", FILES)
    served = make_bare_lab("--allow-local-repos")
    assert post(served, str(repo.path)).status_code == 201
    [mirror] = (served.cache / "mirrors").iterdir()  # the mirror of that repository
    for probe in (
        str(mirror),
        f"file://{mirror}",
        str(served.cache),
        f"{served.data}/../{served.data.name}/blobs",
        str(served.data / "keys"),
        str(served.data / "work" / "trial-1-1"),
    ):
        answer = post(served, probe)
        assert answer.status_code == 422, (probe, answer.text)
        assert "the lab's own" in answer.json()["error"], answer.text
    assert len(served.get("/api/trials")["trials"]) == 1


# -- 4. [data] trials = [2^63] ---------------------------------------------------------------


def test_data_trial_ids_past_2_63_are_a_clear_refusal(
    make_bare_lab: Callable[..., Served], tmp_path: Path
) -> None:
    """lab.toml's [data] naming trial 2^63 (SQLite's integers end at 2^63 - 1) or beyond
    is a 422 that names the trial id and the range, never a 500; 2^31 - 1 (the last id
    PostgreSQL's columns hold) is a trial that does not exist."""
    served = make_bare_lab("--allow-local-repos")
    for trial in (2**63, 2**70, 2**31 - 1):
        toml = f"{TOML}\n[data]\ntrials = [{trial}]\n"
        repo = GitRepo.create(tmp_path / f"learner-{trial}", {**FILES, "lab.toml": toml})
        answer = post(served, str(repo.path))
        assert answer.status_code == 422, (trial, answer.text)
        error: Any = answer.json()["error"]
        assert str(trial) in error, error
        if trial > 2**31 - 1:
            assert "1 to 2147483647" in error, error
        else:
            assert "does not exist" in error, error
