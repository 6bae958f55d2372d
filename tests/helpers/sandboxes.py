"""The sandboxes the tests run controllers in: one runtime cache, one way to make a backend.

Every test that runs a controller (the sandbox's own tests, trials, the service, the
faults) uses the runtime built once into pytest's cache folder from the lab's real client
library, so a cold session builds it once, and parallel workers share it (the build is
locked, see ``sandbox.runtime.build_runtime``).
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

import sandbox
from labd.trial import client_library
from sandbox.api import Backend

BACKENDS = ("bwrap", "docker")


def runtime_cache(config: pytest.Config) -> Path:
    """pytest's cache folder for runtimes, which later sessions reuse (the sandboxes'
    uids must be able to traverse it, as bwrap requires of the lab's data folder)."""
    assert config.cache is not None
    folder = config.cache.mkdir("labd-trials")
    for path in (folder, *folder.parents):
        if not path.stat().st_mode & 0o001:
            pytest.fail(f"{path} must be searchable by others for the sandbox's user")
    folder.chmod(0o755)
    return folder


def make_backend(name: str, cache: Path) -> Backend:
    """The backend ``name`` on the shared runtime; a missing engine skips the test, or
    fails it under ``CI`` (where every backend must be there)."""
    try:
        return sandbox.backend(name, cache, extra_packages=[client_library()])
    except sandbox.BackendUnavailable as err:
        if os.environ.get("CI"):
            pytest.fail(str(err))
        pytest.skip(str(err))
