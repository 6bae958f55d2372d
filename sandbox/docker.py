"""The Docker backend: each job in its own container of the runtime's image.

The image is the runtime's root filesystem, imported once (``docker import`` of a tar of
it) and tagged ``labd-runtime:DIGEST`` by the runtime's digest; nothing is pulled. A
job's container has the launcher as pid 1, runs as uid 64000 with no capabilities and no
new privileges, a read-only root, no network (``network_mode="none"``, the build steps
included: they reach the registry through the lab's proxy alone), and:

    /code          the job's code, bind-mounted read-only
    /mnt/python/N  the job's python_paths, read-only
    /mnt/data      the job's data folder, read-only (LAB_DATA_DIR)
    /scratch       a tmpfs of limits.scratch (and /dev/shm of at most 64 MiB)
    /run/labd/bridge.sock  a controller's: the bridge's unix socket
    /run/labd/proxy.sock   a build step's: the lab's registry proxy (``install.py``)

with ``mem_limit`` = ``memswap_limit``, ``pids_limit``, ``nano_cpus`` and ulimits for open
files, CPU seconds and file size. Its output is streamed through an attach made before
it starts (the log driver is "none": nothing is kept on disk); the wall and output
limits are the backend's; ``State.OOMKilled`` gives ``Exit.out_of_memory``; the
container is removed at the end in every case. The SDK blocks, so every call runs in the
backend's own thread pool and the event loop never waits on the engine.
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import functools
import logging
import os
import shutil
import socket
import tarfile
import tempfile
import time
import uuid
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any, TypeVar

import docker
import docker.errors
import requests
from docker.models.containers import Container
from docker.types import CancellableStream, LogConfig, Mount, Ulimit

from . import runtime as rt
from .api import BackendUnavailable, Exit, Job, MiB, SandboxError
from .install import Step, npm_step, pip_step, run_step, stage_node_package, stage_requirements
from .jobs import (
    JobLog,
    Plan,
    Supervised,
    chown_tree,
    job_plan,
    open_socket,
    start_whole,
    wait_or_stop,
)

log = logging.getLogger(__name__)

IMAGE = "labd-runtime"
LABEL = "org.labd.sandbox"  # on every container of ours: the job's id
OWNER = "org.labd.owner"  # HOST:PID of the lab process that made it
SHM = 64 * MiB
KILLED = 128 + 9  # the exit status of a process ended by SIGKILL
OOM_WAIT = 2.0  # seconds an unexplained SIGKILL waits for the engine to call it an OOM kill
T = TypeVar("T")
ENGINE_HINT = "apt-get install docker.io, then systemctl start docker"
_ENGINE_ERRORS = (docker.errors.DockerException, requests.RequestException, OSError)


class DockerBackend:
    """Jobs in Docker containers."""

    name = "docker"

    def __init__(
        self, runtime: rt.Runtime, client: docker.DockerClient | None = None, max_jobs: int = 16
    ) -> None:
        self.runtime = runtime
        self.client = client or connect()
        # Two threads per job block on its container (its output, its end), one on calls.
        self.executor = ThreadPoolExecutor(2 * max_jobs + 2, thread_name_prefix="labd-docker")
        self.image = f"{IMAGE}:{runtime.digest}"
        self.owner = f"{socket.gethostname()}:{os.getpid()}"
        self._ensure_image()
        self._remove_orphans()

    def runtime_digest(self) -> str:
        return self.runtime.digest

    def close(self) -> None:
        """Let go of the engine connection and the threads (jobs must have ended)."""
        self.executor.shutdown(wait=True)
        self.client.close()

    async def start(self, job: Job) -> DockerRun:
        return await self._start(job_plan(self.runtime, job))

    async def install(self, requirements: Path, target: Path) -> None:
        staging = Path(tempfile.mkdtemp(prefix="labd-install-"))
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
        """Run a build step as the sandbox's uid, which owns ``target`` while it runs."""

        async def run(plan: Plan) -> Exit:
            # a preparing deadline stops the installer too
            return await wait_or_stop(await self._start(plan))

        try:
            chown_tree(target, rt.SANDBOX_UID)
            await run_step(step, run)
        finally:
            chown_tree(target, os.geteuid())

    async def _start(self, plan: Plan) -> DockerRun:
        return await start_whole(self._launch(plan))

    async def _launch(self, plan: Plan) -> DockerRun:
        for path, _ in plan.sockets():
            open_socket(path)
        run = DockerRun(self, f"docker-{uuid.uuid4().hex[:12]}", plan)
        try:
            await run.launch()
        except BaseException:
            await run.abandon()
            raise
        return run

    async def call(self, fn: Callable[..., T], *args: Any, **kwargs: Any) -> T:
        """Run a blocking SDK call in the backend's threads."""
        loop = asyncio.get_running_loop()
        return await loop.run_in_executor(self.executor, functools.partial(fn, *args, **kwargs))

    def container_options(self, job_id: str, plan: Plan) -> dict[str, Any]:
        """The arguments of ``containers.create`` for ``plan``."""
        limits = plan.limits
        mounts = [
            Mount(m.target, str(m.source), type="bind", read_only=not m.writable)
            for m in plan.mounts
        ]
        for path, inside in plan.sockets():
            mounts.append(Mount(inside, str(path), type="bind"))
        uid = str(rt.SANDBOX_UID)
        scratch = f"rw,exec,nosuid,nodev,size={limits.scratch},uid={uid},gid={uid}"
        return {
            "image": self.image,
            "command": list(plan.argv),
            "user": f"{uid}:{uid}",
            "working_dir": "/",
            "hostname": "sandbox",
            "environment": dict(plan.env),
            "network_mode": "none",
            "read_only": True,
            "mounts": mounts,
            # Owned by the sandbox's uid, as bwrap's is (Docker copies the image's mode).
            "tmpfs": {rt.SCRATCH: scratch},
            "shm_size": min(SHM, limits.scratch),
            "mem_limit": limits.memory,
            "memswap_limit": limits.memory,
            "pids_limit": limits.processes,
            "nano_cpus": int(limits.cpus * 1e9),
            "ulimits": [
                Ulimit(name="nofile", soft=limits.open_files, hard=limits.open_files),
                Ulimit(name="cpu", soft=limits.cpu_seconds, hard=limits.cpu_seconds + 1),
                Ulimit(name="fsize", soft=limits.scratch, hard=limits.scratch),
                Ulimit(name="core", soft=0, hard=0),
            ],
            "cap_drop": ["ALL"],
            "security_opt": ["no-new-privileges"],
            "init": False,  # the launcher is pid 1, as under bwrap
            "labels": {LABEL: job_id, OWNER: self.owner},
            "log_config": LogConfig(type="none"),
            "stdin_open": False,
            "tty": False,
        }

    def _ensure_image(self) -> None:
        """Import the runtime as an image, unless it is there already."""
        with contextlib.suppress(docker.errors.ImageNotFound):
            self.client.images.get(self.image)
            return
        log.info("importing the runtime %s into Docker", self.runtime.digest[:12])
        with tempfile.TemporaryDirectory(dir=self.runtime.root.parent) as tmp:
            archive = Path(tmp) / "rootfs.tar"
            _tar(self.runtime.root, archive)
            try:
                self.client.api.import_image_from_file(
                    str(archive),
                    repository=IMAGE,
                    tag=self.runtime.digest,
                    changes=[f"LABEL org.labd.runtime={self.runtime.digest}"],
                )
                self.client.images.get(self.image)
            except _ENGINE_ERRORS as err:
                raise BackendUnavailable("docker", f"cannot import the runtime: {err}") from err

    def _remove_orphans(self) -> None:
        """Remove containers of ours whose lab process on this host is gone.

        The engine's list is read as it is (``api.containers``), not container by
        container: other labs on the machine remove theirs meanwhile, and one gone
        between the list and its inspection must not stop this lab from starting.
        """
        host = socket.gethostname()
        for found in self.client.api.containers(all=True, filters={"label": LABEL}):
            labels = found.get("Labels") or {}
            owner_host, _, pid = str(labels.get(OWNER, "")).rpartition(":")
            if owner_host == host and pid.isdigit() and not Path(f"/proc/{pid}").exists():
                log.warning("removing the orphaned sandbox container %s", found["Id"][:12])
                with contextlib.suppress(*_ENGINE_ERRORS):
                    self.client.api.remove_container(found["Id"], force=True)


class DockerRun(Supervised):
    """A job running in a Docker container."""

    def __init__(self, backend: DockerBackend, job_id: str, plan: Plan) -> None:
        super().__init__(plan.limits, JobLog(log, job_id))
        self.backend = backend
        self.job_id = job_id
        self.plan = plan
        self.container: Container | None = None
        self._pump: asyncio.Future[None] | None = None
        self._status: int | None = None  # the container's exit status, once it ended
        self._killed = False  # the lab sent it SIGKILL

    async def launch(self) -> None:
        call = self.backend.call
        options = self.backend.container_options(self.job_id, self.plan)
        try:
            self.container = await call(self.backend.client.containers.create, **options)
            assert self.container is not None
            # Attached before it starts, so not a byte of its output is missed.
            container = self.container
            stream = await call(
                lambda: container.attach(stdout=True, stderr=True, stream=True, demux=True)
            )
            loop = asyncio.get_running_loop()
            self._pump = loop.run_in_executor(self.backend.executor, self._read, stream, loop)
            await call(self.container.start)
        except _ENGINE_ERRORS as err:
            raise SandboxError(f"Docker could not start the job: {err}") from err
        self.log.info("started in container %s", self.container.short_id)
        self.begin()

    async def abandon(self) -> None:
        """Undo a launch that failed half way."""
        await self._cleanup()

    def _read(
        self,
        stream: CancellableStream[tuple[bytes | None, bytes | None]],
        loop: asyncio.AbstractEventLoop,
    ) -> None:
        """Copy the attached output into ``self.output`` (in a thread, until it ends)."""
        output = self.output
        try:
            for out, err in stream:
                if out:
                    loop.call_soon_threadsafe(output.feed, output.stdout, out)
                if err:
                    loop.call_soon_threadsafe(output.feed, output.stderr, err)
        except _ENGINE_ERRORS as error:  # the container went away under the stream
            self.log.debug("output stream ended: %s", error)
        finally:
            stream.close()
            # close() shuts the socket but leaves the HTTP response (and so the socket's
            # file) open; the SDK says the caller closes the response.
            response = getattr(stream, "_response", None)
            if response is not None:
                response.close()

    async def _ended(self) -> int:
        assert self.container is not None
        result = await self.backend.call(self.container.wait)
        self._status = int(result["StatusCode"])
        return self._status

    async def _terminate(self) -> None:
        await self._send("SIGTERM")

    async def _kill(self) -> None:
        self._killed = True
        await self._send("SIGKILL")

    async def _send(self, signame: str) -> None:
        assert self.container is not None
        try:
            await self.backend.call(self.container.kill, signal=signame)
        except docker.errors.APIError as err:  # it ended meanwhile
            self.log.debug("could not send %s: %s", signame, err)

    async def _drained(self) -> None:
        if self._pump is not None:
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(asyncio.shield(self._pump), 5.0)

    async def _out_of_memory(self) -> bool:
        """Docker's ``OOMKilled``. The engine learns of an OOM kill apart from the exit,
        and on a busy host after it: a job that died of a SIGKILL the lab did not send
        (status 137) is given ``OOM_WAIT`` seconds for the flag to be set."""
        assert self.container is not None
        deadline = time.monotonic() + OOM_WAIT
        while True:
            await self.backend.call(self.container.reload)
            if self.container.attrs["State"].get("OOMKilled"):
                return True
            if self._status != KILLED or self._killed or time.monotonic() > deadline:
                return False
            await asyncio.sleep(0.1)

    async def _cleanup(self) -> None:
        if self.container is None:
            return
        try:
            await self.backend.call(self.container.remove, force=True)
        except docker.errors.NotFound:
            pass
        except _ENGINE_ERRORS as err:
            self.log.error("could not remove container %s: %s", self.container.short_id, err)
            raise


def connect() -> docker.DockerClient:
    """A client of the engine at ``DOCKER_HOST`` (else the local socket) that answered.

    It needs no runtime, so the chooser asks it before building one. BackendUnavailable
    says why not in a few words and what would make an engine answer.
    """
    where = os.environ.get("DOCKER_HOST", "unix:///var/run/docker.sock")
    client: docker.DockerClient | None = None
    try:
        _knock(where)
        client = docker.from_env(timeout=120)
        client.ping()
    except _ENGINE_ERRORS as err:
        if client is not None:
            client.close()
        why, hint = _why(err)
        reason = f"no Docker engine answers at {where} ({why})"
        raise BackendUnavailable("docker", reason, hint) from err
    return client


def _why(err: BaseException) -> tuple[str, str]:
    """Why no engine answered, in a few words (the operating system's reason, which the
    SDK wraps three or four deep, else the SDK's first line), and what fixes that."""
    cause: BaseException | None = err
    while cause is not None:
        if isinstance(cause, OSError) and cause.strerror:
            if cause.errno in (errno.EACCES, errno.EPERM):
                return "permission denied", "adduser $USER docker, then log in again"
            if cause.errno == errno.ECONNREFUSED:
                return "connection refused", "systemctl start docker"
            return cause.strerror.lower(), ENGINE_HINT
        cause = cause.__cause__ or cause.__context__
    return (str(err).splitlines() or [type(err).__name__])[0][:160], ENGINE_HINT


def _knock(where: str) -> None:
    """Connect to a unix-socket engine once, so a missing one fails here, tidily.

    (The SDK leaves the socket of a failed connection open.)
    """
    if where.startswith("unix://"):
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as probe:
            probe.settimeout(10)
            probe.connect(where.removeprefix("unix://"))


def _tar(rootfs: Path, archive: Path) -> None:
    """A tar of ``rootfs`` owned by root, in a fixed order."""
    with tarfile.open(archive, "w") as tar:
        for path in [rootfs, *rt.walk(rootfs)]:
            info = tar.gettarinfo(str(path), arcname=path.relative_to(rootfs).as_posix() or ".")
            info.uid = info.gid = 0
            info.uname = info.gname = "root"
            if info.isfile():
                with path.open("rb") as f:
                    tar.addfile(info, f)
            else:
                tar.addfile(info)
