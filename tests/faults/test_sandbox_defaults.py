"""The sandbox's limits, hit at their documented defaults (docs/trials.md).

tests/sandbox/test_limits.py checks each mechanism with small values; here a job runs
with ``Limits()`` as a trial does and meets the numbers themselves: 256 open files,
64 processes and threads, 256 MiB of scratch, 8 MiB of output, 1 GiB of memory. The
wall time (600 s) and CPU time (3,600 s) are too long for a test: their mechanisms are
checked there, their values in test_documented_limits.
"""

from __future__ import annotations

import asyncio
import json
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path

import pytest

from sandbox.api import Exit, Job, Limits, MiB
from sandbox.jobs import KEEP
from tests.helpers.sandboxes import make_backend

pytestmark = pytest.mark.integration

COUNTS = """\
import errno, json, os, threading
report = {}
fds = []
try:
    while True:
        fds.append(os.open("/dev/null", os.O_RDONLY))
except OSError as err:
    report["files"] = [len(fds), errno.errorcode[err.errno]]
for fd in fds:
    os.close(fd)
stop, threads = threading.Event(), []
try:
    while True:
        thread = threading.Thread(target=stop.wait)
        thread.start()
        threads.append(thread)
except RuntimeError:
    report["threads"] = len(threads)
stop.set()
for thread in threads:
    thread.join()
written = 0
try:
    with open(os.path.join(os.environ["TMPDIR"], "big"), "wb") as out:
        while written < 512 * 2**20:
            out.write(b"x" * 2**20)
            out.flush()
            written += 2**20
except OSError as err:
    report["scratch"] = [written // 2**20, errno.errorcode[err.errno]]
print(json.dumps(report))
"""
OUTPUT = """\
import sys
print("first line", flush=True)
while True:
    sys.stdout.buffer.write((b"x" * 1023 + b"\\n") * 1024)
"""
MEMORY = """\
blocks = []
while True:
    blocks.append(bytearray(64 * 2**20))  # touched: bytearray zeroes its memory
"""


@pytest.fixture
def workdir() -> Iterator[Path]:
    """A folder the sandbox's uid may traverse (pytest's own tmp_path is 0700)."""
    base = Path(tempfile.mkdtemp(prefix="labd-fault-sandbox-"))
    base.chmod(0o755)
    yield base
    shutil.rmtree(base, ignore_errors=True)


def run(cache: Path, workdir: Path, source: str) -> Exit:
    code = workdir / f"code-{len(list(workdir.iterdir()))}"
    code.mkdir(mode=0o755)
    (code / "controller.py").write_text(source)
    job = Job(command=("python", "controller.py"), code=code, bridge_socket=None, limits=Limits())
    backend = make_backend("bwrap", cache)

    async def go() -> Exit:
        running = await backend.start(job)
        return await asyncio.wait_for(running.wait(), 120)

    return asyncio.run(go())


@pytest.mark.timeout(150)
def test_open_files_processes_and_scratch_at_their_defaults(cache: Path, workdir: Path):
    """256 open files (a few are the runtime's), 64 processes and threads (the launcher
    and the main thread among them), 256 MiB of scratch: each the limit, no more."""
    ended = run(cache, workdir, COUNTS)
    assert ended.code == 0, ended.stderr
    report = json.loads(ended.stdout)
    print("at the sandbox's defaults:", report)
    files, reason = report["files"]
    assert reason == "EMFILE" and 240 <= files <= 253, report
    assert 48 <= report["threads"] < 64, report
    mebibytes, reason = report["scratch"]
    assert reason in ("ENOSPC", "EFBIG") and 240 <= mebibytes <= 256, report


@pytest.mark.timeout(150)
def test_output_past_8_mib_is_cut_keeping_64_kib_each_end(cache: Path, workdir: Path):
    """Printing without end is killed past 8 MiB; the first and last 64 KiB are kept."""
    ended = run(cache, workdir, OUTPUT)
    assert ended.output_exceeded and ended.code is None
    assert ended.stdout.startswith(b"first line\n")
    assert b"bytes left out by the sandbox" in ended.stdout
    assert 2 * KEEP <= len(ended.stdout) < 2 * KEEP + 200
    assert Limits().output == 8 * MiB


@pytest.mark.timeout(150)
def test_memory_past_1_gib_is_out_of_memory(cache: Path, workdir: Path):
    """Allocating without end stops at 1 GiB: killed out of memory."""
    ended = run(cache, workdir, MEMORY)
    print("allocating without end:", "out of memory" if ended.out_of_memory else "MemoryError")
    assert ended.out_of_memory or b"MemoryError" in ended.stderr, ended
    assert ended.code != 0
