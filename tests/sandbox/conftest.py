"""Fixtures for the sandbox tests: the session's runtime, a bridge, controllers to run,
a proxy standing in for the host's own.

The runtime and both backends are the ones every test shares (tests/conftest.py): built
once into pytest's cache folder (a minute when cold). The folders the sandboxes mount live
under a base folder that other uids may traverse, as the bwrap backend requires of the
lab's data folder.
"""

from __future__ import annotations

import asyncio
import contextlib
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

from labd.trial import client_library
from sandbox.api import Backend, Exit, Job, Limits, Running
from sandbox.bwrap import BwrapRun, processes_of
from sandbox.docker import LABEL, DockerBackend, DockerRun
from sandbox.runtime import Runtime, build_runtime


@pytest.fixture(scope="session")
def workdir() -> Iterator[Path]:
    """A base folder for the session that the sandboxes' uids may traverse."""
    base = Path(tempfile.mkdtemp(prefix="labd-sandbox-tests-"))
    base.chmod(0o755)
    yield base
    shutil.rmtree(base, ignore_errors=True)


@pytest.fixture(scope="session")
def extra_packages() -> list[Path]:
    """What the lab ships into the runtime beside its Python: the client library."""
    return [client_library()]


@pytest.fixture(scope="session")
def runtime(cache: Path, extra_packages: list[Path]) -> Runtime:
    """The session's runtime (built once into the shared cache, see tests/conftest.py)."""
    return build_runtime(cache, extra_packages)


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
        assert running.container is not None
        assert processes_in_container(running.container.id) == []
    else:  # pragma: no cover
        raise AssertionError(f"unknown run {running!r}")


def processes_in_container(container_id: str) -> list[int]:
    """Host pids still in the container's cgroup, zombies left out: this job's own, not
    those of the sandbox's uid, which other labs' Docker jobs on the host share."""
    found = []
    for entry in os.scandir("/proc"):
        if not entry.name.isdigit():
            continue
        try:
            cgroup = Path(f"/proc/{entry.name}/cgroup").read_text()
            state = Path(f"/proc/{entry.name}/stat").read_text().rsplit(")", 1)[1].split()[0]
        except OSError:  # it ended meanwhile
            continue
        if container_id in cgroup and state != "Z":
            found.append(int(entry.name))
    return found


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


@dataclass
class Upstream:
    """The host's own proxy: records each request head, then does what it asks (a tunnel
    for CONNECT, the request forwarded as it is otherwise)."""

    heads: list[bytes] = field(default_factory=list)
    refuse: bool = False
    server: asyncio.Server | None = None

    @property
    def port(self) -> int:
        assert self.server is not None
        return int(self.server.sockets[0].getsockname()[1])

    async def handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        head = await reader.readuntil(b"\r\n\r\n")
        self.heads.append(head)
        if self.refuse:
            writer.write(b"HTTP/1.1 407 Proxy Authentication Required\r\n\r\n")
            writer.close()
            return
        method, target, _ = head.split(b"\r\n", 1)[0].decode().split(" ")
        hostport = target if method == "CONNECT" else target.split("/")[2]
        host, port = hostport.rsplit(":", 1)
        far_reader, far_writer = await asyncio.open_connection(host, int(port))
        if method == "CONNECT":
            writer.write(b"HTTP/1.1 200 Connection established\r\n\r\n")
        else:
            far_writer.write(head)

        async def pump(source: asyncio.StreamReader, sink: asyncio.StreamWriter) -> None:
            with contextlib.suppress(OSError):
                while data := await source.read(1 << 16):
                    sink.write(data)
                    await sink.drain()
            sink.close()

        await asyncio.gather(pump(reader, far_writer), pump(far_reader, writer))


@pytest.fixture
async def upstream() -> AsyncIterator[Upstream]:
    """A proxy standing in for the one the lab's host may have to go through."""
    made = Upstream()
    made.server = await asyncio.start_server(made.handle, "127.0.0.1", 0)
    yield made
    made.server.close()
