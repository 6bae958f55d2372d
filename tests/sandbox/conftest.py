"""Fixtures for the sandbox tests: one runtime for the session, both backends, a bridge.

The runtime is built once per session into a temporary cache (a minute when cold). The
folders the sandboxes mount live under a base folder that other uids may traverse, as
the bwrap backend requires of the lab's data folder.
"""

from __future__ import annotations

import asyncio
import os
import shutil
import tempfile
import textwrap
import time
import uuid
from collections.abc import AsyncIterator, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import pytest
import websockets.asyncio.server as ws_server

import sandbox
from sandbox.api import Backend, Exit, Job, Limits, Running
from sandbox.bwrap import BwrapRun, processes_of
from sandbox.docker import LABEL, DockerBackend, DockerRun
from sandbox.runtime import SANDBOX_UID, Runtime, build_runtime

BACKENDS = ("docker", "bwrap")
CONTROLLERS_NAME = "labd-test-controllers"


@pytest.fixture(scope="session")
def workdir() -> Iterator[Path]:
    """A base folder for the session that the sandboxes' uids may traverse."""
    base = Path(tempfile.mkdtemp(prefix="labd-sandbox-tests-"))
    base.chmod(0o755)
    yield base
    shutil.rmtree(base, ignore_errors=True)


@pytest.fixture(scope="session")
def extra_packages(workdir: Path) -> list[Path]:
    """A stand-in for the lab's ``controllers`` client library."""
    package = workdir / "extra" / "controllers"
    package.mkdir(parents=True)
    (package / "__init__.py").write_text(f'NAME = "{CONTROLLERS_NAME}"\n')
    return [package]


@pytest.fixture(scope="session")
def cache(request: pytest.FixtureRequest, workdir: Path) -> Path:
    """The runtime cache: pytest's cache folder, so later sessions reuse the runtime."""
    if request.config.cache is not None:
        folder = request.config.cache.mkdir("labd-sandbox")
        if all(p.stat().st_mode & 0o001 for p in folder.parents):
            folder.chmod(0o755)
            return folder
    return workdir / "cache"  # a cold build in every session


@pytest.fixture(scope="session")
def runtime(cache: Path, extra_packages: list[Path]) -> Runtime:
    built = build_runtime(cache, extra_packages)
    for other in cache.glob("runtime-*"):  # runtimes of earlier versions of the code
        if other != built.root.parent:
            shutil.rmtree(other, ignore_errors=True)
    return built


@pytest.fixture(scope="session", params=BACKENDS)
def backend(
    request: pytest.FixtureRequest, runtime: Runtime, cache: Path, extra_packages: list[Path]
) -> Iterator[Backend]:
    """Each backend in turn, made once per session through ``sandbox.backend``."""
    try:
        made = sandbox.backend(request.param, cache, extra_packages)
    except sandbox.BackendUnavailable as err:
        if os.environ.get("CI"):
            pytest.fail(str(err))
        pytest.skip(str(err))
    yield made
    if isinstance(made, DockerBackend):
        made.close()


@dataclass
class Bridge:
    """A WebSocket server on a host unix socket, standing in for the lab's bridge.

    It answers ``echo:MESSAGE`` to every message, but ``barrier:N`` waits until N
    connections have sent it, then answers ``go`` to each. ``received`` has every message.
    """

    socket: Path
    received: asyncio.Queue[str] = field(default_factory=asyncio.Queue)
    _arrived: int = 0
    _everyone: asyncio.Event = field(default_factory=asyncio.Event)

    async def handle(self, ws: ws_server.ServerConnection) -> None:
        async for message in ws:
            assert isinstance(message, str)
            await self.received.put(message)
            if message.startswith("barrier:"):
                self._arrived += 1
                if self._arrived >= int(message.split(":")[1]):
                    self._everyone.set()
                await self._everyone.wait()
                await ws.send("go")
            else:
                await ws.send(f"echo:{message}")


@pytest.fixture
async def bridge(workdir: Path) -> AsyncIterator[Bridge]:
    path = workdir / f"bridge-{uuid.uuid4().hex[:8]}.sock"
    bridge = Bridge(path)
    async with ws_server.unix_serve(bridge.handle, str(path), max_size=None):
        yield bridge
    path.unlink(missing_ok=True)


class Controllers:
    """Write controllers into code folders and run them in a backend."""

    def __init__(self, backend: Backend, workdir: Path) -> None:
        self.backend = backend
        self.workdir = workdir

    def code(self, source: str, **files: str) -> Path:
        folder = self.workdir / f"code-{uuid.uuid4().hex[:8]}"
        folder.mkdir(mode=0o755)
        (folder / "controller.py").write_text(textwrap.dedent(source))
        for name, text in files.items():
            (folder / name).write_text(textwrap.dedent(text))
        return folder

    async def start(
        self,
        source: str,
        limits: Limits | None = None,
        bridge: Bridge | None = None,
        python_paths: Sequence[Path] = (),
        env: dict[str, str] | None = None,
        command: Sequence[str] = ("python", "controller.py"),
        data: Path | None = None,
    ) -> Running:
        job = Job(
            command=command,
            code=self.code(source),
            bridge_socket=bridge.socket if bridge else None,
            env=env or {},
            python_paths=python_paths,
            limits=limits or Limits(wall=60),
            data=data,
        )
        return await self.backend.start(job)

    async def run(self, source: str, **kwargs: object) -> Exit:
        """Run a controller to its end; check that nothing of it is left."""
        running = await self.start(source, **kwargs)  # type: ignore[arg-type]
        ended = await running.wait()
        assert_nothing_left(self.backend, running)
        return ended


def assert_nothing_left(backend: Backend, running: Running) -> None:
    """No process of the job's uid survives, and (Docker) no container of it remains."""
    if isinstance(running, BwrapRun):
        assert processes_of(running.host_uid) == []
    elif isinstance(running, DockerRun):
        assert isinstance(backend, DockerBackend)
        left = backend.client.containers.list(
            all=True, filters={"label": f"{LABEL}={running.job_id}"}
        )
        assert left == []
        assert processes_of(SANDBOX_UID) == []
    else:  # pragma: no cover
        raise AssertionError(f"unknown run {running!r}")


@pytest.fixture
def controllers(backend: Backend, workdir: Path) -> Controllers:
    return Controllers(backend, workdir)


def lines(data: bytes) -> list[str]:
    return data.decode().splitlines()


async def wait_for(queue: asyncio.Queue[str], expected: str, timeout: float = 30) -> None:
    """Wait until ``expected`` arrives on ``queue`` (other messages are skipped)."""
    deadline = time.monotonic() + timeout
    while True:
        message = await asyncio.wait_for(queue.get(), deadline - time.monotonic())
        if message == expected:
            return
