"""Isolation backends behind one interface: Docker and bubblewrap.

``backend()`` builds (or reuses) the controller runtime and returns the backend to run
jobs with: Docker wherever an engine answers, else bubblewrap, or the one named. The
interface is in ``api.py``; the runtime both backends share in ``runtime.py``; the first
process of every job in ``launcher.py``; the build steps (pip, npm) in ``install.py``, and
the proxy that is their only way to the registry in ``proxy.py``. Imports no other
package of the lab.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path

from .api import (
    BRIDGE_PORT,
    Backend,
    BackendUnavailable,
    Exit,
    InstallError,
    Job,
    Limits,
    NoSandbox,
    Running,
    RuntimeBuildError,
    SandboxError,
)
from .bwrap import BwrapBackend
from .bwrap import tools as bwrap_tools
from .docker import DockerBackend
from .docker import connect as connect_engine
from .runtime import Runtime, build_runtime

log = logging.getLogger(__name__)

BACKENDS = ("docker", "bwrap")


def backend(name: str | None, cache: Path, extra_packages: Sequence[Path] = ()) -> Backend:
    """The backend called ``name`` (None: Docker if an engine answers, else bwrap).

    Builds the controller runtime into ``cache`` first if it is not there (a minute or
    so, once per set of inputs), and imports it into Docker if needed: call it at start-up,
    not from a running event loop. ``extra_packages`` are folders copied into the
    runtime's site-packages (the lab's controller client library).

    What each backend needs of the machine (an engine that answers; bwrap on PATH) is
    asked before that build, so a machine with neither says so at once: NoSandbox, with
    each one's reason and what to install.
    """
    if name is not None and name not in BACKENDS:
        raise BackendUnavailable(name, f"no such backend; choose one of {', '.join(BACKENDS)}")
    cache = Path(cache).resolve()  # engines mount absolute paths only
    tried: list[BackendUnavailable] = []
    client = None
    if name in (None, "docker"):
        try:
            client = connect_engine()
        except BackendUnavailable as err:
            if name == "docker":
                raise
            tried.append(err)
    if client is None:
        try:
            bwrap_tools()
        except BackendUnavailable as err:
            if name == "bwrap":
                raise
            raise NoSandbox([*tried, err]) from err
    try:
        runtime = build_runtime(cache, extra_packages)
    except BaseException:
        if client is not None:
            client.close()
        raise
    if client is not None:
        try:
            return DockerBackend(runtime, client)
        except BackendUnavailable as err:  # the engine answered, yet cannot take the runtime
            client.close()
            if name == "docker":
                raise
            tried.append(err)
    for skipped in tried:
        log.info("%s; using bubblewrap", skipped)
    try:
        return BwrapBackend(runtime, cache / "bwrap")
    except BackendUnavailable as err:
        if name == "bwrap":
            raise
        raise NoSandbox([*tried, err]) from err


__all__ = [
    "BACKENDS",
    "BRIDGE_PORT",
    "Backend",
    "BackendUnavailable",
    "BwrapBackend",
    "DockerBackend",
    "Exit",
    "InstallError",
    "Job",
    "Limits",
    "NoSandbox",
    "Running",
    "Runtime",
    "RuntimeBuildError",
    "SandboxError",
    "backend",
    "build_runtime",
]
