"""Controllers in JavaScript: Node.js and roslibjs in both sandboxes, npm packages installed
in the build step from the repository's lock file, Node's errors as a trial's reason."""

from __future__ import annotations

import asyncio
import hashlib
import json
import shutil
from pathlib import Path

import pytest

from labd.replay import replay
from repository.trial import Order, Outcome
from sandbox.api import Limits, MiB
from scheduler.runner import RunOptions, run_trial
from tests.helpers.sandboxes import BACKENDS, make_backend

pytestmark = pytest.mark.integration
NODE = Path(__file__).resolve().parent / "node"
SHORT = {"time_limit": 3}  # 30 ticks of the maze
# The stepper with a package of its own: ms, pinned by a lock file.
PACKAGE = {"name": "stepper", "private": True, "type": "module", "dependencies": {"ms": "2.1.3"}}
LOCK = {
    "name": "stepper",
    "lockfileVersion": 3,
    "requires": True,
    "packages": {
        "": {"name": "stepper", "dependencies": {"ms": "2.1.3"}},
        "node_modules/ms": {
            "version": "2.1.3",
            "integrity": "sha512-6FlzubTLZG3J2a/NVCAleEhjzq5oxgHyaCU9yYXvcLsvoVaHJq/s5xXI6/"
            "XXP6tz7R9xAOtHnSO/tXtF3WRTlA==",
            "license": "MIT",
        },
    },
}


def stepper(tmp_path: Path, *args: str, package: bool = False, lock: bool = True) -> Path:
    """A copy of the stepper controller whose command passes ``args``."""
    folder = tmp_path / f"stepper-{len(list(tmp_path.glob('stepper-*')))}"
    shutil.copytree(NODE / "stepper", folder)
    command = json.dumps(["node", "controller.mjs", *args])
    (folder / "lab.toml").write_text(f'[controller]\ncommand = {command}\ntask = "icreate-maze"\n')
    if package:
        (folder / "package.json").write_text(json.dumps(PACKAGE, indent=2))
        if lock:
            (folder / "package-lock.json").write_text(json.dumps(LOCK, indent=2))
    for path in [folder, *folder.iterdir()]:
        path.chmod(0o755 if path.is_dir() else 0o644)
    return folder


def run(backend, cache, host, tmp_path, source, options=None, params=SHORT, **kwargs):
    order = Order(repository=str(source), params=dict(params), **kwargs)
    out = tmp_path / f"run-{len(list(tmp_path.glob('run-*')))}"
    return asyncio.run(
        run_trial(
            order, backend=backend, host=host, out=out, cache=cache, options=options or RunOptions()
        )
    )


def test_a_javascript_controller_runs_in_lockstep_and_reproduces(backend, cache, host, tmp_path):
    """A roslibjs controller under Node steps the maze to the episode's end, and the same
    seed gives the same data again; another seed gives other data."""
    folder = stepper(tmp_path)
    first = run(backend, cache, host, tmp_path, folder, seed=3)
    assert first.outcome is Outcome.FAIL, first.reason
    assert "the episode ended at tick 30" in first.reason
    assert (
        "the episode ended after 30 ticks" in (first.folder / "controller.stderr.log").read_text()
    )
    again = run(backend, cache, host, tmp_path, folder, seed=3)
    assert again.data_digest == first.data_digest
    assert run(backend, cache, host, tmp_path, folder, seed=4).data_digest != first.data_digest
    assert replay(first.mcap).verified


def test_both_sandboxes_give_a_javascript_controller_the_same_data(cache, host, tmp_path):
    """The same JavaScript trial under bubblewrap and under Docker: one data digest."""
    folder = stepper(tmp_path)
    digests = {
        run(make_backend(name, cache), cache, host, tmp_path, folder, seed=5).data_digest
        for name in BACKENDS
    }
    assert len(digests) == 1


@pytest.mark.parametrize(
    ("how", "reason"),
    [
        (
            ["crash"],
            "the controller exited with 1 at tick 3: Error: the controller broke on purpose"
            " (/code/controller.mjs, line",
        ),
        (["package"], "the controller exited with 1 at tick 0: Error [ERR_MODULE_NOT_FOUND]"),
        (["hang"], "stalled at tick 3: no /lab/step for 3 s"),
    ],
    ids=["crash", "missing-module", "hang"],
)
def test_a_broken_javascript_controller_is_an_error_saying_why(
    backend, cache, host, tmp_path, how, reason
):
    """A Node crash names its error and line; an import of a package that is not there
    names it; a controller that stops stepping is stopped."""
    options = RunOptions(limits=Limits(memory=512 * MiB, wall=60.0), stall=3.0, first_step=10.0)
    result = run(backend, cache, host, tmp_path, stepper(tmp_path, *how), options=options)
    assert result.outcome is Outcome.ERROR
    assert reason in result.reason, result.reason


def test_npm_packages_install_from_the_lock_file(backend, host, tmp_path):
    """A repository's package-lock.json is installed in the build step (npm ci, with the
    network, in the sandbox), its digest goes into the manifest, and roslib stays there."""
    cache = tmp_path / "cache"  # a cache of its own: the install happens here, not earlier
    folder = stepper(tmp_path, "package", package=True)
    result = run(backend, cache, host, tmp_path, folder, seed=1)
    assert result.outcome is Outcome.FAIL, result.reason  # ran to the episode's end
    assert 'ms("2 minutes") is 120000' in (result.folder / "controller.stderr.log").read_text()
    manifest = json.loads((result.folder / "manifest.json").read_text())
    lock = (folder / "package-lock.json").read_bytes()
    assert manifest["controller"]["node_packages_sha256"] == hashlib.sha256(lock).hexdigest()
    installed = list((cache / "node").iterdir())
    assert len(installed) == 1 and (installed[0] / "node_modules" / "ms").is_dir()
    again = run(backend, cache, host, tmp_path, folder, seed=1)  # from the cache
    assert again.data_digest == result.data_digest
    assert list((cache / "node").iterdir()) == installed


@pytest.mark.parametrize(
    ("lock", "reason"),
    [
        (True, "npm packages: No matching version found for ms@99.0.0"),
        (False, "npm packages: package.json names dependencies (ms) but the repository has no"),
    ],
    ids=["unknown-version", "no-lock-file"],
)
def test_npm_packages_that_cannot_install_are_the_trials_error(cache, host, tmp_path, lock, reason):
    """A lock file naming what the registry does not have, or no lock file, ends the trial
    as an error with npm's reason in one line, and nothing is left in the cache."""
    backend = make_backend(BACKENDS[0], cache)
    cache = tmp_path / "cache"  # the trials' own: nothing of an earlier install
    folder = stepper(tmp_path, "package", package=True, lock=lock)
    for name in ("package.json", "package-lock.json"):
        if (folder / name).exists():
            (folder / name).write_text((folder / name).read_text().replace("2.1.3", "99.0.0"))
    result = run(backend, cache, host, tmp_path, folder)
    assert result.outcome is Outcome.ERROR
    assert reason in result.reason, result.reason
    assert "\n" not in result.reason
    assert not list(cache.glob("node/*"))
