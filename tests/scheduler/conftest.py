"""Fixtures for trials for real: the runtime cache, both sandboxes, the lab's side."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

import sandbox
from labd.trial import LabHost, client_library
from sandbox.api import Backend

BACKENDS = ["bwrap", "docker"]


@pytest.fixture(scope="session")
def cache(request: pytest.FixtureRequest) -> Path:
    """pytest's cache folder, so later sessions reuse the runtime (bwrap needs o+x on it)."""
    assert request.config.cache is not None
    folder = request.config.cache.mkdir("labd-trials")
    for path in (folder, *folder.parents):
        if not path.stat().st_mode & 0o001:
            pytest.fail(f"{path} must be searchable by others for the sandbox's user")
    folder.chmod(0o755)
    return folder


def make_backend(name: str, cache: Path) -> Backend:
    try:
        return sandbox.backend(name, cache, extra_packages=[client_library()])
    except sandbox.BackendUnavailable as err:
        if os.environ.get("CI"):
            pytest.fail(str(err))
        pytest.skip(str(err))


@pytest.fixture(scope="session", params=BACKENDS)
def backend(request: pytest.FixtureRequest, cache: Path) -> Backend:
    return make_backend(request.param, cache)


@pytest.fixture(scope="session")
def host() -> LabHost:
    return LabHost()
