"""The sandboxes the tests run controllers in: one runtime cache, one way to make a backend.

Every test that runs a controller (the sandbox's own tests, trials, the service, the
faults) uses the runtime built once into pytest's cache folder from the lab's real client
library, so a cold session builds it once, and parallel workers share it (the build is
locked, see ``sandbox.runtime.build_runtime``).

That folder lies inside the checkout, which may lie under a folder only its owner may enter
(a 0700 home, as Debian makes them). The sandboxes reach it as they reach a lab's data
folder there (docs/trials.md): Docker's engine mounts as root; bubblewrap run as root binds
it in each job's own mount namespace (``sandbox/views.py``), and run as another user is
that user. So the tests run from such a clone as the lab would, through the same binds.
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
    """pytest's cache folder for runtimes, which later sessions reuse: wherever the
    checkout is, searchable by others or not (the sandboxes reach it, see above)."""
    assert config.cache is not None
    folder = config.cache.mkdir("labd-trials")
    folder.chmod(0o755)  # whatever the umask: other uids read the runtimes once they reach it
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
