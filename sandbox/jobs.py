"""What every backend does the same way: the launch plan, bounded output, supervision.

A ``Plan`` is a job as a backend runs it: the launcher's argv and environment, what to
mount where, and the unix sockets bound under ``/run/labd`` (the trial's bridge for a
controller, the lab's registry proxy for a build step, ``install.py``). No plan has a
network of its own: every sandbox has only its own loopback. ``Supervised``
is the shared half of a running job: it enforces the wall and output limits, carries
out ``stop()``, and turns a backend's raw exit status into an ``Exit``; the backend
supplies how its sandbox ends, is signalled, and is cleaned up.
"""

from __future__ import annotations

import abc
import asyncio
import contextlib
import logging
import os
import signal
import stat
import time
from collections.abc import Coroutine, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

from . import runtime as rt
from .api import BRIDGE_PORT, Exit, Job, Limits, SandboxError

KEEP = 64 * 1024  # bytes kept of the beginning and of the end of each stream

NODE_COMMANDS = frozenset({"node", "nodejs", "npm", "npx"})


@dataclass(frozen=True)
class Mount:
    """A host path seen inside the sandbox."""

    source: Path
    target: str
    writable: bool = False


@dataclass(frozen=True)
class Plan:
    """One sandboxed run as a backend carries it out."""

    argv: tuple[str, ...]  # the launcher's command line
    env: Mapping[str, str]
    mounts: tuple[Mount, ...]  # besides the runtime as / and the scratch tmpfs
    bridge_socket: Path | None  # a controller's: the trial's bridge
    limits: Limits
    proxy_socket: Path | None = None  # a build step's: the lab's proxy to the registry

    def sockets(self) -> list[tuple[Path, str]]:
        """The host's unix sockets the sandbox is given, and where it finds each."""
        found = [(self.bridge_socket, rt.BRIDGE_SOCKET), (self.proxy_socket, rt.PROXY_SOCKET)]
        return [(host, inside) for host, inside in found if host is not None]


def environment(
    runtime: rt.Runtime, bridge: bool, python_paths: int, extra: Mapping[str, str]
) -> dict[str, str]:
    """The environment of the launcher and the controller (the same in every backend)."""
    paths = [f"{rt.PYTHON_PATHS}/{i}" for i in range(python_paths)]
    env = {
        "PATH": f"{Path(runtime.python).parent}:/usr/local/bin:/usr/bin:/bin",
        "HOME": rt.HOME,
        "TMPDIR": rt.TMPDIR,
        "USER": "sandbox",
        "LOGNAME": "sandbox",
        "LANG": "C.UTF-8",
        "PYTHONPATH": ":".join([*paths, rt.SITE_PACKAGES]),
        "PYTHONDONTWRITEBYTECODE": "1",
        "PYTHONNOUSERSITE": "1",
        # One BLAS thread: the same sums in the same order, so trials replay bit for bit.
        "OPENBLAS_NUM_THREADS": "1",
        "OMP_NUM_THREADS": "1",
    }
    if bridge:
        env["LAB_BRIDGE_URL"] = f"ws://127.0.0.1:{BRIDGE_PORT}"
        # The same, in the two parts roslibpy.Ros(host=..., port=...) takes.
        env["LAB_BRIDGE_HOST"] = "127.0.0.1"
        env["LAB_BRIDGE_PORT"] = str(BRIDGE_PORT)
        # The bridge's own unix socket, for a client that can skip the launcher's relay
        # (the lab's client library does).
        env["LAB_BRIDGE_SOCKET"] = rt.BRIDGE_SOCKET
    env.update(extra)
    return env


def launcher_argv(
    runtime: rt.Runtime, command: Sequence[str], cwd: str, relay: tuple[str, int] | None
) -> tuple[str, ...]:
    """The launcher's command line; ``relay`` (a unix socket inside, a port) makes it relay
    ``127.0.0.1:port`` to that socket (the bridge, or a build step's proxy)."""
    argv = [runtime.python, "-I", "-S", rt.LAUNCHER, "--cwd", cwd]
    argv += ["--mkdir", rt.HOME, "--mkdir", rt.TMPDIR]
    if relay is not None:
        argv += ["--bridge", relay[0], "--port", str(relay[1])]
    return (*argv, "--", *command)


def job_plan(runtime: rt.Runtime, job: Job) -> Plan:
    """The plan of a controller job: its code, its python paths, the bridge; no network."""
    if not job.command:
        raise SandboxError("the job has no command")
    if runtime.node is None and Path(job.command[0]).name in NODE_COMMANDS:
        raise SandboxError(
            f"cannot run {job.command[0]!r}: this lab's sandbox has no Node.js (the lab's"
            f" host needs node {rt.NODE_MAJOR} or later, with npm, when the runtime is built)"
        )
    bridge = job.bridge_socket is not None
    if job.bridge_socket is not None and not job.bridge_socket.is_socket():
        raise SandboxError(f"the bridge socket {job.bridge_socket} does not exist")
    mounts = [Mount(job.code.resolve(), rt.CODE)]
    for i, path in enumerate(job.python_paths):
        mounts.append(Mount(Path(path).resolve(), f"{rt.PYTHON_PATHS}/{i}"))
    env = environment(runtime, bridge, len(job.python_paths), job.env)
    if job.data is not None:
        mounts.append(Mount(job.data.resolve(), rt.DATA))
        env["LAB_DATA_DIR"] = rt.DATA
    if job.node_modules is not None:
        mounts.append(Mount(job.node_modules.resolve(), rt.SHARED_NODE_MODULES))
    for mount in mounts:
        if not mount.source.is_dir():
            raise SandboxError(f"{mount.source} is not a folder")
    return Plan(
        argv=launcher_argv(
            runtime, job.command, rt.CODE, (rt.BRIDGE_SOCKET, BRIDGE_PORT) if bridge else None
        ),
        env=env,
        mounts=tuple(mounts),
        bridge_socket=job.bridge_socket.resolve() if job.bridge_socket else None,
        limits=job.limits,
    )


S = TypeVar("S", bound="Supervised")


async def start_whole(starting: Coroutine[Any, Any, S]) -> S:
    """Start a job as one step: a cancellation that comes while it starts (a trial's lease
    lost, a deadline passed) lets the start finish, stops the job, and then goes on.

    Cancelled half way, a start leaves what it started behind: an asyncio subprocess
    cancelled while its pipes are being connected never reports its end, so stopping it
    waits forever (CPython gh-103847), and a Docker container that an engine thread
    creates after its caller gave up is never removed. A start ends within its own
    deadlines (bwrap's set-up, the engine's timeout), so the wait is bounded.
    """
    task = asyncio.ensure_future(starting)
    try:
        return await asyncio.shield(task)
    except asyncio.CancelledError:
        with contextlib.suppress(Exception):  # a start that failed cleaned up after itself
            run = await task
            await run.stop(grace=0)
        raise


async def wait_or_stop(run: Supervised) -> Exit:
    """Wait for a job's end; if the waiter is cancelled (a deadline passed), stop the job
    first, so no sandbox outlives what it was started for."""
    try:
        return await run.wait()
    except asyncio.CancelledError:
        await run.stop(grace=0.5)
        raise


class Stream:
    """The beginning and the end of one output stream, and how much there was."""

    def __init__(self, keep: int = KEEP) -> None:
        self.keep = keep
        self.total = 0
        self._head = bytearray()
        self._tail = bytearray()

    def feed(self, data: bytes) -> None:
        self.total += len(data)
        room = self.keep - len(self._head)
        if room > 0:
            self._head += data[:room]
            data = data[room:]
        if data:
            self._tail += data[-self.keep :]
            if len(self._tail) > self.keep:
                del self._tail[: len(self._tail) - self.keep]

    def value(self) -> bytes:
        left_out = self.total - len(self._head) - len(self._tail)
        if left_out <= 0:
            return bytes(self._head + self._tail)
        marker = f"\n[... {left_out} bytes left out by the sandbox ...]\n".encode()
        return bytes(self._head) + marker + bytes(self._tail)


class Output:
    """stdout and stderr of a job, bounded; ``exceeded`` is set past ``limit`` bytes."""

    def __init__(self, limit: int) -> None:
        self.limit = limit
        self.stdout = Stream()
        self.stderr = Stream()
        self.exceeded = asyncio.Event()

    def feed(self, stream: Stream, data: bytes) -> None:
        stream.feed(data)
        if self.stdout.total + self.stderr.total > self.limit:
            self.exceeded.set()


def chown_tree(root: Path, uid: int) -> None:
    """Give ``root`` and all below it to ``uid`` (and its group), if we may."""
    if os.geteuid() != 0:
        return
    os.lchown(root, uid, uid)
    for dirpath, dirnames, filenames in os.walk(root):
        for name in (*dirnames, *filenames):
            os.lchown(os.path.join(dirpath, name), uid, uid)


def open_socket(path: Path) -> None:
    """Let the sandbox's uid connect to a socket it is given: others may read and write it.

    Only the job that mounts it can see it; on the host the lab runs as root.
    """
    mode = stat.S_IMODE(path.stat().st_mode)
    if mode & 0o006 != 0o006:
        path.chmod(mode | 0o006)


class JobLog(logging.LoggerAdapter[logging.Logger]):
    """A logger that names the job in every message."""

    def __init__(self, logger: logging.Logger, job_id: str) -> None:
        super().__init__(logger, {"job": job_id})
        self.job_id = job_id

    def process(self, msg: object, kwargs: Any) -> tuple[object, Any]:
        return f"[{self.job_id}] {msg}", kwargs


def decode_status(status: int) -> tuple[int | None, int | None]:
    """(code, signal) from the launcher's exit status, or -N for a process killed by N."""
    if status < 0:
        return None, -status
    if status > 128 and status - 128 in set(signal.Signals):
        return None, status - 128
    return status, None


class Supervised(abc.ABC):
    """A running job: limits, ``stop()`` and the ``Exit``, shared by the backends."""

    def __init__(self, limits: Limits, log: JobLog) -> None:
        self.limits = limits
        self.log = log
        self.output = Output(limits.output)
        self._stop = asyncio.Event()
        self._grace = 2.0
        self._started = time.monotonic()
        self._task: asyncio.Task[Exit] | None = None

    def begin(self) -> None:
        """Start supervising; the backend calls it once its sandbox runs."""
        self._started = time.monotonic()
        self._task = asyncio.get_running_loop().create_task(self._supervise())

    async def wait(self) -> Exit:
        """Wait for the end (the wall limit included) and clean everything up."""
        assert self._task is not None
        return await asyncio.shield(self._task)

    async def stop(self, grace: float = 2.0) -> Exit:
        """Ask it to stop (SIGTERM), kill it after ``grace`` seconds, clean up."""
        self._grace = grace
        self._stop.set()
        return await self.wait()

    # What a backend provides.
    @abc.abstractmethod
    async def _ended(self) -> int:
        """Wait until the sandbox has ended; its exit status (see ``decode_status``)."""

    @abc.abstractmethod
    async def _terminate(self) -> None:
        """Send SIGTERM to the launcher (which forwards it to the controller)."""

    @abc.abstractmethod
    async def _kill(self) -> None:
        """End every process of the job now."""

    @abc.abstractmethod
    async def _drained(self) -> None:
        """Wait until all the output has been read."""

    @abc.abstractmethod
    async def _out_of_memory(self) -> bool:
        """Whether the kernel killed a process of the job for memory."""

    @abc.abstractmethod
    async def _cleanup(self) -> None:
        """Remove what the job leaves (processes, cgroups, containers); always called."""

    async def _supervise(self) -> Exit:
        loop = asyncio.get_running_loop()
        ended = loop.create_task(self._ended())
        exceeded = loop.create_task(self.output.exceeded.wait())
        stopped = loop.create_task(self._stop.wait())
        killed = output_exceeded = wall_exceeded = False
        try:
            done, _ = await asyncio.wait(
                {ended, exceeded, stopped},
                timeout=self.limits.wall,
                return_when=asyncio.FIRST_COMPLETED,
            )
            if ended not in done:
                if exceeded in done:
                    output_exceeded = killed = True
                    self.log.info("output past %d bytes: killing the job", self.limits.output)
                    await self._kill()
                elif stopped in done:
                    self.log.info("stopping the job (grace %.1f s)", self._grace)
                    await self._terminate()
                    try:
                        await asyncio.wait_for(asyncio.shield(ended), self._grace)
                    except TimeoutError:
                        killed = True
                        await self._kill()
                else:
                    wall_exceeded = killed = True
                    self.log.info(
                        "past the wall limit of %.1f s: killing the job", self.limits.wall
                    )
                    await self._kill()
            status = await ended
            await self._drained()
            out_of_memory = await self._out_of_memory()
        finally:
            for task in (ended, exceeded, stopped):
                task.cancel()
            await self._cleanup()
        code, signum = (None, int(signal.SIGKILL)) if killed else decode_status(status)
        result = Exit(
            code=code,
            signal=signum,
            out_of_memory=out_of_memory,
            output_exceeded=output_exceeded or self.output.exceeded.is_set(),
            wall_exceeded=wall_exceeded,
            cpu_exceeded=signum == signal.SIGXCPU,
            stdout=self.output.stdout.value(),
            stderr=self.output.stderr.value(),
            seconds=time.monotonic() - self._started,
        )
        self.log.info(
            "ended: code %s signal %s%s in %.2f s",
            result.code,
            result.signal,
            "".join(
                f" {flag}"
                for flag in ("out_of_memory", "output_exceeded", "wall_exceeded", "cpu_exceeded")
                if getattr(result, flag)
            ),
            result.seconds,
        )
        return result


async def drain_within(tasks: Sequence[asyncio.Task[None]], seconds: float) -> None:
    """Wait for reader tasks, then cancel whatever is still reading."""
    if not tasks:
        return
    _, pending = await asyncio.wait(tasks, timeout=seconds)
    for task in pending:
        task.cancel()
    for task in pending:
        with contextlib.suppress(asyncio.CancelledError):
            await task
