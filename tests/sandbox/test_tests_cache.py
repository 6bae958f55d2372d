"""The tests' runtime cache in a clone under a folder only its owner may enter.

``make test`` from a checkout in a 0700 home folder (as Debian makes new users' homes)
keeps the runtime in pytest's cache inside that checkout; the sandboxes must reach it
there as they reach a lab's data folder (``sandbox/views.py``), and the helper that
hands the folder out must not refuse it.
"""

from __future__ import annotations

import shutil
from pathlib import Path
from types import SimpleNamespace
from typing import cast

import pytest

import sandbox
from sandbox.api import Job, Limits
from sandbox.runtime import Runtime
from tests.helpers.sandboxes import runtime_cache
from tests.sandbox.conftest import assert_nothing_left

pytestmark = pytest.mark.timeout(300)


def checkout_in_private_home(workdir: Path, name: str) -> Path:
    """pytest's cache folder of a checkout in a 0700 home: ``HOME/labd/.pytest_cache/d``."""
    home = workdir / name
    (home / "labd" / ".pytest_cache" / "d").mkdir(parents=True)
    home.chmod(0o700)
    return home / "labd" / ".pytest_cache" / "d"


@pytest.mark.integration
async def test_a_clone_under_a_private_folder_runs_its_sandboxes(
    runtime: Runtime, workdir: Path, extra_packages: list[Path]
) -> None:
    """The runtime cache under a 0700 folder is handed out, bubblewrap is chosen on it
    (its probe runs a job from there) and a controller runs from it."""
    if shutil.which("bwrap") is None:
        pytest.skip("no bwrap on this machine")
    pytest_cache = checkout_in_private_home(workdir, "home-tests-cache")

    def mkdir(name: str) -> Path:  # as pytest's Cache.mkdir
        (pytest_cache / name).mkdir(exist_ok=True)
        return pytest_cache / name

    config = SimpleNamespace(cache=SimpleNamespace(mkdir=mkdir))
    try:
        folder = runtime_cache(cast(pytest.Config, config))
        assert folder == pytest_cache / "labd-trials"
        # the session's runtime, as if built there (a build takes a minute)
        (folder / runtime.root.parent.name).symlink_to(runtime.root.parent)
        backend = sandbox.backend("bwrap", folder, extra_packages)
        code = folder.parent / "code"
        code.mkdir()
        (code / "controller.py").write_text("import numpy; print('ran', numpy.__name__)\n")
        running = await backend.start(
            Job(["python", "controller.py"], code, None, limits=Limits(wall=60))
        )
        ended = await running.wait()
        assert_nothing_left(backend, running)
        assert ended.code == 0, ended.stderr
        assert ended.stdout == b"ran numpy\n"
    finally:
        shutil.rmtree(pytest_cache.parents[2], ignore_errors=True)
