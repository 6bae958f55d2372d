"""The sandbox interface: what the trial runner asks of an isolation backend.

A ``Job`` is one command to run isolated: the controller's code read-only, the
data it learns from read-only (``LAB_DATA_DIR``), a scratch folder, no network but
the one way to the trial's bridge (a unix socket on the host, reached inside as
``ws://127.0.0.1:9090``), limits on CPU, memory, processes, open
files, output and wall time, and every process gone at the end. Backends (Docker,
bubblewrap) run the same controller runtime, so a trial gives the same data with
either.

    SandboxError                 the sandbox could not do what was asked
    ├── BackendUnavailable       no Docker engine answers / no bwrap on this machine
    │   └── NoSandbox            neither: each one's reason and what to install
    ├── RuntimeBuildError        the controller runtime could not be built
    └── InstallError             a repository's requirements could not be installed
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

# Bytes. Its own, as sandbox imports no other package of ours; the rest of the lab
# takes it from repository.units.
MiB = 1 << 20
BRIDGE_PORT = 9090  # inside the sandbox: ws://127.0.0.1:9090
PROXY_PORT = 3128  # inside a build step's sandbox: the lab's proxy to the registry


class SandboxError(Exception):
    """The sandbox could not do what was asked."""


class BackendUnavailable(SandboxError):
    """``backend`` cannot run here: ``reason`` says why in a few words, ``hint`` (if any)
    what to run on Debian to fix it."""

    def __init__(self, backend: str, reason: str, hint: str = "") -> None:
        self.backend = backend
        self.reason = reason
        self.hint = hint
        fix = f" (on Debian: {hint})" if hint else ""
        super().__init__(f"the {backend} sandbox is not available: {reason}{fix}")


class NoSandbox(BackendUnavailable):
    """No backend can run here: the chooser tried each in turn. One message holds every
    reason and every fix, since one fix is enough and only the reader can tell which."""

    def __init__(self, tried: Sequence[BackendUnavailable]) -> None:
        self.tried = tuple(tried)
        reasons = ", and ".join(err.reason for err in self.tried)
        hints = "; or ".join(err.hint for err in self.tried if err.hint)
        fix = f" To fix it on Debian: {hints}." if hints else ""
        SandboxError.__init__(
            self,
            f"no sandbox can run controllers here: {reasons}.{fix} The lab takes Docker"
            " where an engine answers, else bubblewrap; --sandbox docker|bwrap names one.",
        )
        self.backend = ", ".join(err.backend for err in self.tried)
        self.reason = reasons
        self.hint = hints


class RuntimeBuildError(SandboxError):
    def __init__(self, reason: str) -> None:
        self.reason = reason
        super().__init__(f"the controller runtime could not be built: {reason}")


class InstallError(SandboxError):
    """pip failed on a repository's requirements; ``log`` is the end of its output."""

    def __init__(self, reason: str, log: str = "") -> None:
        self.reason = reason
        self.log = log
        super().__init__(f"the requirements could not be installed: {reason}")


@dataclass(frozen=True)
class Limits:
    """What a sandboxed job may use."""

    cpus: float = 1.0  # share of CPUs while it runs
    cpu_seconds: int = 3600  # CPU time in all, then it is killed
    memory: int = 1024 * MiB  # bytes of memory
    processes: int = 64  # processes and threads at once
    open_files: int = 256
    output: int = 8 * MiB  # bytes of stdout and stderr; more and it is killed
    wall: float = 600.0  # seconds; more and it is killed
    scratch: int = 256 * MiB  # bytes of the writable scratch folder


@dataclass(frozen=True)
class Job:
    """One command to run isolated."""

    command: Sequence[str]  # argv, run with /code as the working directory
    code: Path  # host folder, mounted read-only at /code
    bridge_socket: Path | None  # host unix socket; inside it is ws://127.0.0.1:9090
    env: Mapping[str, str] = field(default_factory=dict)  # added to the runtime's
    python_paths: Sequence[Path] = ()  # host folders mounted read-only, put on PYTHONPATH
    limits: Limits = field(default_factory=Limits)
    data: Path | None = None  # host folder mounted read-only at LAB_DATA_DIR (/mnt/data)
    node_modules: Path | None = None  # host folder mounted read-only at /node_modules


@dataclass(frozen=True)
class Exit:
    """How a job ended.

    ``code`` is the exit status (None if killed by a signal, then ``signal`` says
    which). The flags say why the sandbox killed it, if it did. ``stdout`` and
    ``stderr`` are bounded: the beginning and the end of each, with a marker between
    where the middle was left out.
    """

    code: int | None
    signal: int | None = None
    out_of_memory: bool = False
    output_exceeded: bool = False
    wall_exceeded: bool = False
    cpu_exceeded: bool = False
    stdout: bytes = b""
    stderr: bytes = b""
    seconds: float = 0.0


class Running(Protocol):
    """A job in progress."""

    async def wait(self) -> Exit:
        """Wait for the end (the wall limit included) and clean everything up."""
        ...

    async def stop(self, grace: float = 2.0) -> Exit:
        """Ask it to stop (SIGTERM), kill it after ``grace`` seconds, clean up."""
        ...


class Backend(Protocol):
    """An isolation backend."""

    name: str  # "docker" or "bwrap"

    def runtime_digest(self) -> str:
        """sha256 naming the controller runtime (Python and its packages) jobs run in."""
        ...

    async def install(self, requirements: Path, target: Path) -> None:
        """pip-install ``requirements`` into ``target``, in the sandbox.

        Only wheels are accepted (no code of the repository's runs at install time). The
        sandbox has no network of its own: pip reaches the configured package index
        alone, through the lab's proxy (``install.py``). InstallError says why it failed.
        """
        ...

    async def install_node(self, package: Path, lock: Path, target: Path) -> None:
        """``npm ci`` of ``package`` (package.json) and ``lock`` (package-lock.json)
        into ``target``, in the sandbox, with no install scripts run, reaching the
        configured registry alone (through the lab's proxy, as ``install()`` does).

        ``target/node_modules`` is then what a job mounts as its ``node_modules``;
        InstallError says why it failed.
        """
        ...

    async def start(self, job: Job) -> Running:
        """Start ``job``; BackendUnavailable if this backend cannot run here."""
        ...
