"""The bubblewrap backend: each job in its own namespaces, as its own unprivileged uid.

``bwrap`` runs as a host uid leased to the job alone (64100 and up), unprivileged: it
makes a user namespace where the job is uid 64000 (as under Docker), and new mount, pid,
network, ipc, uts and cgroup namespaces (``--unshare-all``): every job, the build steps
included, has only a loopback network of its own, never the host's. Inside:

    /              the runtime, read-only          /code         the job's code, read-only
    /scratch       a tmpfs of limits.scratch       /mnt/python/N the job's python_paths
    /mnt/data      the job's data, read-only (LAB_DATA_DIR)
    /proc, /dev    the namespace's own (/dev read-only but a small /dev/shm)
    /run/labd/bridge.sock                          a controller's: the bridge's unix socket
    /run/labd/proxy.sock                           a build step's: the lab's registry proxy

The launcher is pid 1 (``--as-pid-1``), so when it ends the kernel ends every process of
the job; ``--die-with-parent`` ends it with the lab. bwrap starts under ``prlimit``, which
sets the job's rlimits (processes of its uid, open files, CPU seconds, file size; the
address space only where no memory cgroup could be made), and waits on ``--block-fd``
while the backend moves the launcher into the job's cgroup (memory, pids, CPU quota;
``cgroups.py``). At the end the backend kills whatever still runs as the job's uid,
removes the cgroup and gives the uid back.

bwrap opens the mounted paths as the job's uid. Where one of them is out of that uid's
reach (under a 0700 home folder, say), a lab run as root binds it where the uid can reach
it, in a mount namespace of the job's own (``views.py``); a lab run as another user runs
bwrap as itself, and ``start()`` says which folder it cannot search.
"""

from __future__ import annotations

import asyncio
import contextlib
import fcntl
import json
import logging
import os
import shutil
import signal
import subprocess
import tempfile
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from . import runtime as rt
from .api import BackendUnavailable, Exit, Job, Limits, MiB, SandboxError
from .cgroups import JobCgroup
from .install import Step, npm_step, pip_step, run_step, stage_node_package, stage_requirements
from .jobs import (
    JobLog,
    Plan,
    Stream,
    Supervised,
    chown_tree,
    drain_within,
    job_plan,
    open_socket,
    start_whole,
    wait_or_stop,
)
from .views import Views, refusal, unreachable

log = logging.getLogger(__name__)

UIDS = range(64100, 64356)  # host uids leased to jobs, one each
# The uids' locks, one folder for the whole machine: a lab that leases a uid kills what
# still runs as it, so two labs (labd serve, and labd run with another --data) must
# never lease the same uid. /run is root's alone, and only a lab run as root leases.
UID_LOCKS = Path("/run/labd/sandbox-uids")
SHM = 64 * MiB  # /dev/shm, as Docker's default
SETUP_TIMEOUT = 60.0  # seconds bwrap may take to make a sandbox


class UidLease:
    """A host uid held by one job (a lock file, so other lab processes skip it too)."""

    def __init__(self, uid: int, fd: int) -> None:
        self.uid = uid
        self._fd = fd

    def release(self) -> None:
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1


class UidPool:
    """Host uids for jobs; a uid is free when no lab process holds its lock."""

    def __init__(self, folder: Path, uids: range = UIDS) -> None:
        self.folder = folder
        self.uids = uids
        folder.mkdir(parents=True, exist_ok=True)

    def lease(self) -> UidLease:
        for uid in self.uids:
            fd = os.open(self.folder / f"{uid}.lock", os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o600)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                os.close(fd)
                continue
            kill_uid(uid)  # what a crashed lab may have left as this uid
            return UidLease(uid, fd)
        raise SandboxError(f"all {len(self.uids)} sandbox uids are in use")


def processes_of(uid: int) -> list[int]:
    """Host pids whose real uid is ``uid``, zombies left out (they have ended already).

    When the launcher is killed, the kernel ends the rest of the namespace and hands the
    dead to the host's init to reap, which may take it a moment.
    """
    found = []
    for entry in os.scandir("/proc"):
        if not entry.name.isdigit():
            continue
        try:
            with open(f"/proc/{entry.name}/status", "rb") as f:
                fields = dict(line.split(b":", 1) for line in f if b":" in line)
        except OSError:  # it ended meanwhile
            continue
        if int(fields[b"Uid"].split()[0]) == uid and not fields[b"State"].strip().startswith(b"Z"):
            found.append(int(entry.name))
    return found


def kill_uid(uid: int, timeout: float = 5.0) -> None:
    """SIGKILL every process of ``uid`` until none is left (blocking)."""
    deadline = time.monotonic() + timeout
    while pids := processes_of(uid):
        for pid in pids:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
        if time.monotonic() > deadline:
            raise SandboxError(f"processes of uid {uid} survive SIGKILL: {pids}")
        time.sleep(0.005)


def sources(rootfs: Path, plan: Plan) -> list[Path]:
    """Every host path bwrap mounts for ``plan``, the runtime ``rootfs`` first."""
    return [rootfs, *(m.source for m in plan.mounts), *(host for host, _ in plan.sockets())]


@dataclass(frozen=True)
class Start:
    """How to start bwrap's command line: the argv, and whom the child becomes."""

    argv: list[str]
    user: int | None = None  # None: stay who the lab is
    extra_groups: list[int] | None = None

    @classmethod
    def as_job(cls, argv: list[str], uid: int, privileged: bool, views: Views) -> Start:
        """Start ``argv`` as the job's ``uid`` and group alone, when the lab is root:
        through the views' mount namespace when there are binds (``setpriv`` becomes
        ``uid`` once they are made), else by the subprocess itself. Otherwise bwrap
        runs as the lab's own uid."""
        if privileged and views.binds:
            return cls(views.command(argv, uid))
        if privileged:
            return cls(argv, uid, [])
        return cls(argv)


def tools(bwrap: str = "bwrap") -> tuple[str, str]:
    """Where ``bwrap`` and ``prlimit`` are; BackendUnavailable, saying what to install,
    without them. It needs no runtime, so the chooser asks it before building one."""
    found = shutil.which(bwrap)
    if found is None:
        raise BackendUnavailable("bwrap", f"no {bwrap} on PATH", "apt-get install bubblewrap")
    prlimit = shutil.which("prlimit")
    if prlimit is None:
        raise BackendUnavailable("bwrap", "no prlimit on PATH", "apt-get install util-linux")
    return found, prlimit


class BwrapBackend:
    """Jobs in bubblewrap sandboxes."""

    name = "bwrap"

    def __init__(
        self, runtime: rt.Runtime, state: Path, bwrap: str = "bwrap", uid_locks: Path = UID_LOCKS
    ) -> None:
        self.runtime = runtime
        self.state = state
        self.bwrap, self.prlimit = tools(bwrap)
        self.privileged = os.geteuid() == 0
        state.mkdir(parents=True, exist_ok=True)
        self.uids = UidPool(uid_locks) if self.privileged else None
        self._probe()

    def runtime_digest(self) -> str:
        return self.runtime.digest

    async def start(self, job: Job) -> BwrapRun:
        return await self._start(job_plan(self.runtime, job))

    async def install(self, requirements: Path, target: Path) -> None:
        staging = Path(tempfile.mkdtemp(prefix="install-", dir=self.state))
        try:
            staged = stage_requirements(requirements, staging)
            target.mkdir(parents=True, exist_ok=True)
            step = await asyncio.to_thread(pip_step, self.runtime, staged, target)
            await self._install(step, target)
        finally:
            shutil.rmtree(staging, ignore_errors=True)

    async def install_node(self, package: Path, lock: Path, target: Path) -> None:
        target.mkdir(parents=True, exist_ok=True)
        stage_node_package(package, lock, target)
        await self._install(await asyncio.to_thread(npm_step, self.runtime, target), target)

    async def _install(self, step: Step, target: Path) -> None:
        """Run a build step as a leased uid that owns ``target`` while it runs."""
        lease = self._lease()

        async def run(plan: Plan) -> Exit:
            # a preparing deadline stops the installer too
            return await wait_or_stop(await self._start(plan, lease))

        try:
            chown_tree(target, lease.uid)
            await run_step(step, run)
        finally:
            chown_tree(target, os.geteuid())
            lease.release()

    def _lease(self) -> UidLease:
        return self.uids.lease() if self.uids is not None else UidLease(os.getuid(), -1)

    async def _start(self, plan: Plan, lease: UidLease | None = None) -> BwrapRun:
        return await start_whole(self._launch(plan, lease))

    async def _launch(self, plan: Plan, lease: UidLease | None) -> BwrapRun:
        own_lease = lease is None
        if lease is None:
            lease = await asyncio.to_thread(self._lease)
        job_id = f"bwrap-{uuid.uuid4().hex[:12]}"
        run = BwrapRun(job_id, plan, lease, own_lease)
        try:
            run.views = await asyncio.to_thread(self._views, plan, lease.uid)
            for path, _ in plan.sockets():
                open_socket(path)
            await run.launch(self.bwrap, self.prlimit, self.runtime.root, self.privileged)
        except BaseException:
            await run.abandon()
            raise
        return run

    def _views(self, plan: Plan, uid: int) -> Views:
        """Where bwrap, run as ``uid``, finds the paths of ``plan`` (see ``views.py``)."""
        paths = sources(self.runtime.root, plan)
        if self.privileged:
            return Views.make(paths, uid)
        for path in paths:  # bwrap runs as the lab's own uid: nothing to bind with
            if (blocked := unreachable(path, uid)) is not None:
                raise refusal(path, blocked, uid)
        return Views()

    def _probe(self) -> None:
        """Run ``true`` in a sandbox, so a machine that cannot says why now."""
        lease = self._lease()
        plan = _probe_plan()
        try:
            views = self._views(plan, lease.uid)
        except SandboxError as err:
            lease.release()
            raise BackendUnavailable("bwrap", str(err)) from None
        try:
            argv = bwrap_argv(self.bwrap, self.runtime.root, plan, where=views.path)
            start = Start.as_job(argv, lease.uid, self.privileged, views)
            done = subprocess.run(  # noqa: S603 - our own command line
                start.argv,
                capture_output=True,
                text=True,
                env={},
                timeout=30,
                check=False,
                user=start.user,
                group=start.user,
                extra_groups=start.extra_groups,
            )
        finally:
            views.remove()
            lease.release()
        if done.returncode != 0:
            raise BackendUnavailable("bwrap", done.stderr.strip() or f"exit {done.returncode}")


class BwrapRun(Supervised):
    """A job running in a bubblewrap sandbox."""

    def __init__(self, job_id: str, plan: Plan, lease: UidLease, own_lease: bool) -> None:
        super().__init__(plan.limits, JobLog(log, job_id))
        self.job_id = job_id
        self.plan = plan
        self.host_uid = lease.uid
        self._lease = lease
        self._own_lease = own_lease
        self._proc: asyncio.subprocess.Process | None = None
        self._child: int | None = None  # the launcher's host pid
        self._cgroup: JobCgroup | None = None
        self._readers: list[asyncio.Task[None]] = []
        self.views = Views()  # the backend sets them before launching

    async def launch(self, bwrap: str, prlimit: str, rootfs: Path, privileged: bool) -> None:
        limits = self.plan.limits
        if privileged:
            self._cgroup = await asyncio.to_thread(JobCgroup.create, f"labd-{self.job_id}", limits)
        info_r, info_w = os.pipe()
        block_r, block_w = os.pipe()
        try:
            argv = prlimit_argv(prlimit, limits, memory=self._cgroup is None)
            argv += bwrap_argv(
                bwrap, rootfs, self.plan, info_fd=info_w, block_fd=block_r, where=self.views.path
            )
            # bwrap runs as the job's uid and group alone, unprivileged
            start = Start.as_job(argv, self.host_uid, privileged, self.views)
            self._proc = await asyncio.create_subprocess_exec(
                *start.argv,
                stdin=subprocess.DEVNULL,
                stdout=subprocess.PIPE,
                stderr=subprocess.PIPE,
                env=dict(self.plan.env),
                pass_fds=(info_w, block_r),
                start_new_session=True,
                cwd="/",
                user=start.user,
                group=start.user,
                extra_groups=start.extra_groups,
            )
            os.close(info_w)
            os.close(block_r)
            info_w = block_r = -1
            fd, info_r = info_r, -1
            try:
                info = await asyncio.wait_for(_read_json(fd), SETUP_TIMEOUT)
            except TimeoutError:
                raise SandboxError(f"bwrap did not set up in {SETUP_TIMEOUT} s") from None
            if info is None:
                _, stderr = await self._proc.communicate()
                raise SandboxError(f"bwrap could not make the sandbox: {stderr.decode().strip()}")
            child = info.get("child-pid")
            if not isinstance(child, int):
                raise SandboxError(f"bwrap said no child pid: {info}")
            self._child = child
            if self._cgroup is not None:
                self._cgroup.add(self._child)
            os.write(block_w, b"1")
        finally:
            for fd in (info_r, info_w, block_r, block_w):
                if fd >= 0:
                    os.close(fd)
        assert self._proc.stdout is not None and self._proc.stderr is not None
        loop = asyncio.get_running_loop()
        self._readers = [
            loop.create_task(self._read(self._proc.stdout, self.output.stdout)),
            loop.create_task(self._read(self._proc.stderr, self.output.stderr)),
        ]
        command = self.plan.argv[self.plan.argv.index("--") + 1 :]
        self.log.info("started as uid %d: %s", self.host_uid, " ".join(command))
        self.begin()

    async def abandon(self) -> None:
        """Undo a launch that failed half way."""
        self._kill_launcher()
        if self._proc is not None:
            await self._proc.wait()
        await self._cleanup()

    async def _read(self, pipe: asyncio.StreamReader, stream: Stream) -> None:
        while data := await pipe.read(1 << 16):
            self.output.feed(stream, data)

    async def _ended(self) -> int:
        assert self._proc is not None
        return await self._proc.wait()

    async def _terminate(self) -> None:
        self._signal(signal.SIGTERM)

    async def _kill(self) -> None:
        # pid 1 of the namespace: its end ends every process in it.
        self._signal(signal.SIGKILL)
        self._kill_launcher()

    def _kill_launcher(self) -> None:
        # os.kill, not Process.kill(): that polls the process first, and a poll that
        # reaps a launcher which just ended takes its status away from asyncio's child
        # watcher, which then reports 255 ("Unknown child process") as how it ended.
        if self._proc is not None and self._proc.returncode is None:
            with contextlib.suppress(ProcessLookupError):
                os.kill(self._proc.pid, signal.SIGKILL)

    def _signal(self, signum: int) -> None:
        if self._child is not None:
            with contextlib.suppress(ProcessLookupError):
                os.kill(self._child, signum)

    async def _drained(self) -> None:
        await drain_within(self._readers, 5.0)

    async def _out_of_memory(self) -> bool:
        return self._cgroup is not None and self._cgroup.oom_kills() > 0

    async def _cleanup(self) -> None:
        for task in self._readers:
            task.cancel()
        if self._proc is not None and self._proc.returncode is None:
            await self._kill()
            await self._proc.wait()
        try:
            if self._lease.uid != os.getuid():
                await asyncio.to_thread(kill_uid, self._lease.uid)
        finally:
            self.views.remove()
            if self._cgroup is not None:
                await asyncio.to_thread(self._cgroup.remove)
            if self._own_lease:
                self._lease.release()


def bwrap_argv(
    bwrap: str,
    rootfs: Path,
    plan: Plan,
    *,
    info_fd: int | None = None,
    block_fd: int | None = None,
    where: Callable[[Path], str] = str,
) -> list[str]:
    """bwrap's command line for ``plan`` with ``rootfs`` as /; ``where`` says where
    bwrap finds a host path (``Views.path``)."""
    limits = plan.limits
    uid = str(rt.SANDBOX_UID)
    argv = [bwrap, "--unshare-all", "--unshare-user", "--disable-userns"]
    argv += ["--die-with-parent", "--as-pid-1", "--new-session", "--hostname", "sandbox"]
    argv += ["--uid", uid, "--gid", uid, "--ro-bind", where(rootfs), "/"]
    argv += ["--proc", "/proc", "--dev", "/dev"]
    shm = str(min(SHM, limits.scratch))
    argv += ["--size", shm, "--tmpfs", "/dev/shm", "--remount-ro", "/dev"]  # noqa: S108
    argv += ["--size", str(limits.scratch), "--tmpfs", rt.SCRATCH]
    under_mnt = [m for m in plan.mounts if m.target.startswith(rt.MNT + "/")]
    if under_mnt:
        argv += ["--tmpfs", rt.MNT]
    for mount in plan.mounts:
        argv += ["--bind" if mount.writable else "--ro-bind", where(mount.source), mount.target]
    if under_mnt:
        argv += ["--remount-ro", rt.MNT]
    if sockets := plan.sockets():
        argv += ["--tmpfs", "/run", "--dir", rt.RUN_DIR]
        for socket, inside in sockets:
            argv += ["--ro-bind", where(socket), inside]
        argv += ["--remount-ro", "/run"]
    argv += ["--chdir", "/"]
    if info_fd is not None:
        argv += ["--info-fd", str(info_fd)]
    if block_fd is not None:
        argv += ["--block-fd", str(block_fd)]
    return [*argv, "--", *plan.argv]


def _probe_plan() -> Plan:
    return Plan(argv=("/bin/sh", "-c", ":"), env={}, mounts=(), bridge_socket=None, limits=Limits())


def prlimit_argv(prlimit: str, limits: Limits, memory: bool) -> list[str]:
    """``prlimit`` setting the job's rlimits on itself, then running the rest of argv.

    The lab may lack CAP_SYS_RESOURCE (it does on this machine), which it would need to
    set another user's limits; a process may always lower its own.
    """
    argv = [
        prlimit,
        f"--nproc={limits.processes}",
        f"--nofile={limits.open_files}",
        f"--cpu={limits.cpu_seconds}:{limits.cpu_seconds + 1}",  # SIGXCPU, then SIGKILL
        f"--fsize={limits.scratch}",
        "--core=0",
    ]
    if memory:  # no memory cgroup: the address space is the next best bound
        argv.append(f"--as={limits.memory}")
    return [*argv, "--"]


async def _read_json(fd: int) -> dict[str, object] | None:
    """Read one JSON object from a pipe (bwrap's --info-fd); None if it closes first."""
    loop = asyncio.get_running_loop()
    reader = asyncio.StreamReader()
    transport, _ = await loop.connect_read_pipe(
        lambda: asyncio.StreamReaderProtocol(reader), os.fdopen(fd, "rb", buffering=0)
    )
    data = b""
    try:
        while chunk := await reader.read(4096):
            data += chunk
            with contextlib.suppress(ValueError):
                value = json.loads(data)
                if isinstance(value, dict):
                    return value
        return None
    finally:
        transport.close()
