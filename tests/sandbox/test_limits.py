"""The limits hold: processes, memory, output, wall time, CPU time, files; stop() ends all."""

from __future__ import annotations

import asyncio
import signal
import subprocess
import time
import uuid

import psutil
import pytest

from sandbox.api import Backend, Job, Limits, MiB
from sandbox.bwrap import BwrapBackend
from sandbox.cgroups import own_cgroups
from sandbox.docker import LABEL, DockerBackend
from sandbox.jobs import KEEP
from tests.sandbox.conftest import Bridge, Controllers, assert_nothing_left, wait_for

pytestmark = [pytest.mark.integration, pytest.mark.timeout(300)]


def memory_cgroups_writable() -> bool:
    folder = own_cgroups().get("memory")
    if folder is None:
        return False
    probe = folder / "labd-probe"
    try:
        probe.mkdir()
    except OSError:
        return False
    probe.rmdir()
    return True


async def test_a_fork_bomb_is_contained(controllers: Controllers) -> None:
    """A fork bomb hits the process limit, is killed at the wall limit, and leaves nothing."""
    started = time.monotonic()
    ended = await controllers.run(
        """
        import os
        while True:
            try:
                os.fork()
            except OSError:
                pass
        """,
        limits=Limits(processes=32, wall=3.0),
    )
    assert ended.wall_exceeded
    assert (ended.code, ended.signal) == (None, signal.SIGKILL)
    assert time.monotonic() - started < 20
    # The host still makes processes.
    assert subprocess.run(["/bin/true"], check=False).returncode == 0


async def test_processes_are_limited(controllers: Controllers) -> None:
    """Past limits.processes, starting another process fails in the controller."""
    ended = await controllers.run(
        """
        import os, time
        children = []
        try:
            for _ in range(100):
                pid = os.fork()
                if pid == 0:
                    time.sleep(30)
                    os._exit(0)
                children.append(pid)
            print("forked", len(children))
        except OSError as err:
            print("refused after", len(children), type(err).__name__)
        """,
        limits=Limits(processes=16, wall=60),
    )
    assert ended.code == 0, ended.stderr
    words = ended.stdout.decode().split()
    assert words[:2] == ["refused", "after"]
    assert 5 <= int(words[2]) < 16
    assert words[3] == "BlockingIOError"


async def test_endless_allocation_ends_out_of_memory(
    controllers: Controllers, backend: Backend
) -> None:
    """Allocating without end ends as out_of_memory (a cgroup), else with a MemoryError."""
    ended = await controllers.run(
        """
        blocks = []
        while True:
            blocks.append(bytearray(8 * 1024 * 1024))
        """,
        limits=Limits(memory=128 * MiB, wall=60),
    )
    if isinstance(backend, BwrapBackend) and not memory_cgroups_writable():
        assert ended.code == 1
        assert b"MemoryError" in ended.stderr
        assert not ended.out_of_memory
    else:
        assert ended.out_of_memory
        assert (ended.code, ended.signal) == (None, signal.SIGKILL)


async def test_flooding_output_is_cut_at_the_limit(controllers: Controllers) -> None:
    """Printing gigabytes is stopped past limits.output; the output kept is bounded."""
    started = time.monotonic()
    ended = await controllers.run(
        """
        import sys
        line = b"x" * 1023 + b"\\n"
        print("first line", flush=True)
        while True:
            sys.stdout.buffer.write(line * 1024)
        """,
        limits=Limits(output=4 * MiB, wall=60),
    )
    assert ended.output_exceeded
    assert (ended.code, ended.signal) == (None, signal.SIGKILL)
    assert ended.stdout.startswith(b"first line\n")
    assert b"bytes left out by the sandbox" in ended.stdout
    assert len(ended.stdout) < 2 * KEEP + 200
    assert time.monotonic() - started < 20


async def test_a_job_past_its_wall_time_is_killed(controllers: Controllers) -> None:
    """A job that hangs past limits.wall is killed and says wall_exceeded."""
    ended = await controllers.run(
        """
        import time
        print("waiting", flush=True)
        time.sleep(600)
        """,
        limits=Limits(wall=1.5),
    )
    assert ended.wall_exceeded
    assert (ended.code, ended.signal) == (None, signal.SIGKILL)
    assert ended.stdout == b"waiting\n"
    assert 1.5 <= ended.seconds < 10


async def test_cpu_time_is_limited(controllers: Controllers) -> None:
    """A controller past limits.cpu_seconds of CPU is stopped with SIGXCPU: cpu_exceeded."""
    ended = await controllers.run(
        """
        while True:
            pass
        """,
        limits=Limits(cpu_seconds=1, wall=30),
    )
    assert ended.cpu_exceeded
    assert (ended.code, ended.signal) == (None, signal.SIGXCPU)


async def test_open_files_are_limited(controllers: Controllers) -> None:
    """Past limits.open_files, opening another file fails with EMFILE."""
    ended = await controllers.run(
        """
        import errno
        files = []
        try:
            while len(files) < 1000:
                files.append(open("/dev/null"))
        except OSError as err:
            print(errno.errorcode[err.errno], len(files) < 64)
        """,
        limits=Limits(open_files=64, wall=30),
    )
    assert ended.code == 0, ended.stderr
    assert ended.stdout == b"EMFILE True\n"


SPAWNER = """
    import os, signal, subprocess, sys, time
    from websockets.sync.client import connect
    signal.signal(signal.SIGTERM, signal.{handler})
    # A child in the controller's process group and one in a session of its own, both
    # running before the controller says it is ready. (start_new_session calls setsid();
    # a second os.setsid() in the child would fail with EPERM and end it at once.)
    sleeper = [sys.executable, "-c", "import time; print('up', flush=True); time.sleep(600)"]
    children = [
        subprocess.Popen(sleeper, stdout=subprocess.PIPE),
        subprocess.Popen(sleeper, stdout=subprocess.PIPE, start_new_session=True),
    ]
    assert [child.stdout.readline() for child in children] == [b"up\\n"] * 2
    with connect(os.environ["LAB_BRIDGE_URL"]) as ws:
        ws.send("ready")
        ws.recv()
    time.sleep(600)
"""


async def test_stop_kills_everything(controllers: Controllers, bridge: Bridge) -> None:
    """stop() of a job that ignores SIGTERM kills it after the grace, with all it started."""
    running = await controllers.start(SPAWNER.format(handler="SIG_IGN"), bridge=bridge)
    await wait_for(bridge.received, "ready")
    started = time.monotonic()
    ended = await running.stop(grace=0.5)
    assert 0.5 <= time.monotonic() - started < 10
    assert (ended.code, ended.signal) == (None, signal.SIGKILL)
    assert not ended.wall_exceeded
    assert_nothing_left(controllers.backend, running)


async def test_stop_asks_first(controllers: Controllers, bridge: Bridge) -> None:
    """stop() sends SIGTERM first: a controller that dies of it ends with SIGTERM."""
    running = await controllers.start(SPAWNER.format(handler="SIG_DFL"), bridge=bridge)
    await wait_for(bridge.received, "ready")
    ended = await running.stop(grace=30)
    assert (ended.code, ended.signal) == (None, signal.SIGTERM)
    assert ended.seconds < 30
    assert_nothing_left(controllers.backend, running)


async def test_what_a_controller_leaves_behind_is_killed(controllers: Controllers) -> None:
    """Processes a controller leaves running when it exits are ended with the job."""
    ended = await controllers.run(
        """
        import subprocess, sys
        # In a session of its own, so that killing the controller's process group misses it.
        sleeper = [sys.executable, "-c", "import time; print('up', flush=True); time.sleep(600)"]
        left = subprocess.Popen(sleeper, stdout=subprocess.PIPE, start_new_session=True)
        print("leaving", left.stdout.readline().decode().strip())
        """,
        limits=Limits(wall=30),
    )
    assert ended.code == 0, ended.stderr
    assert ended.stdout == b"leaving up\n"  # it ran when the controller exited
    assert not ended.wall_exceeded
    assert ended.seconds < 10


async def test_two_jobs_run_at_once(controllers: Controllers, bridge: Bridge) -> None:
    """Two jobs run at the same time: each waits at a barrier only both together pass."""
    source = """
        import os
        from websockets.sync.client import connect
        with connect(os.environ["LAB_BRIDGE_URL"]) as ws:
            ws.send("barrier:2")
            print(ws.recv())
    """
    first = await controllers.start(source, bridge=bridge, limits=Limits(wall=60))
    second = await controllers.start(source, bridge=bridge, limits=Limits(wall=60))
    endings = await asyncio.gather(first.wait(), second.wait())
    for ended in endings:
        assert (ended.code, ended.stdout) == (0, b"go\n"), ended.stderr
    assert_nothing_left(controllers.backend, first)
    assert_nothing_left(controllers.backend, second)


async def test_a_start_cancelled_at_any_moment_leaves_nothing(controllers: Controllers) -> None:
    """A start cancelled at any moment of it (a trial's lease lost while its sandbox
    starts) ends at once and leaves no process nor container; one that had started
    reports how its stop ended it. (Cancelled while asyncio connected the launcher's
    pipes, a start used to wait forever for the launcher it had killed.)"""
    token = f"labd-cancel-{uuid.uuid4().hex}"  # on every process of these jobs' command lines
    job = Job(
        command=("python", "controller.py", token),
        code=controllers.code("import time\ntime.sleep(600)\n"),
        bridge_socket=None,
        limits=Limits(wall=60),
    )
    backend = controllers.backend
    began = time.monotonic()
    await (await backend.start(job)).stop(grace=0)
    whole = time.monotonic() - began  # a start and a stop, on this machine now
    started = 0
    for step in range(16):
        starting = asyncio.create_task(backend.start(job))
        await asyncio.sleep(whole * step / 15)
        starting.cancel()
        done, _ = await asyncio.wait({starting}, timeout=30)
        assert done, f"a start cancelled after {whole * step / 15:.3f} s did not end"
        if not starting.cancelled():
            started += 1
            ended = await starting.result().stop(grace=0)
            assert ended.code is None and ended.signal in (signal.SIGTERM, signal.SIGKILL), ended
    assert started < 16  # some were cancelled while they started
    assert [p.info for p in psutil.process_iter(["pid", "cmdline"]) if token in (p.info["cmdline"] or [])] == []  # fmt: skip
    if isinstance(backend, DockerBackend):
        found = backend.client.api.containers(all=True, filters={"label": LABEL})  # any lab's
        assert [c["Id"] for c in found if token in c.get("Command", "")] == []
