"""Jobs whose every folder lies under a folder only its owner may enter (a 0700 home).

The lab's data folder (runtime, requirements, the backend's state) and the job's code
may live under such a folder: Docker's engine mounts as root; bubblewrap, run as the
job's uid, reaches them through binds in a mount namespace of the job's own
(``sandbox/views.py``), which leave nothing behind.
"""

from __future__ import annotations

import dataclasses
import os
import shutil
import tempfile
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest

from sandbox.api import Backend, BackendUnavailable, Job, Limits, SandboxError
from sandbox.bwrap import UIDS, BwrapBackend
from sandbox.docker import DockerBackend
from sandbox.runtime import Runtime
from sandbox.views import VIEWS, Views
from tests.sandbox.conftest import assert_nothing_left

pytestmark = pytest.mark.timeout(300)

if os.geteuid() != 0:  # as another user bwrap runs as that user, who reaches their folders
    pytest.skip("the lab runs as root here", allow_module_level=True)


@pytest.fixture
def private(workdir: Path) -> Iterator[Path]:
    """A folder only its owner (root) may enter, as a home folder often is."""
    folder = workdir / f"home-{uuid.uuid4().hex[:8]}"
    folder.mkdir()
    folder.chmod(0o700)
    yield folder
    shutil.rmtree(folder)


@pytest.fixture
def views(monkeypatch: pytest.MonkeyPatch) -> Iterator[Path]:
    """The mount points' folder, this test's own: other tests' jobs (and other labs' on
    this machine) come and go in the shared one while this one runs."""
    own = VIEWS / f"test-{uuid.uuid4().hex[:8]}"
    monkeypatch.setattr("sandbox.views.VIEWS", own)
    yield own
    shutil.rmtree(own, ignore_errors=True)


def views_left(views: Path) -> set[Path]:
    return set(views.glob("job-*"))


def backend_in(name: str, runtime: Runtime, private: Path) -> Backend:
    """A backend whose runtime and state are reached through ``private``, as with
    ``labd run --data ~/lab-data`` (the runtime itself is the session's, linked)."""
    cache = private / "lab-data" / "cache"
    cache.mkdir(parents=True)
    link = cache / runtime.root.parent.name
    link.symlink_to(runtime.root.parent)
    there = dataclasses.replace(runtime, root=link / "rootfs")
    if name == "bwrap" and shutil.which("bwrap") is None:
        pytest.skip("no bwrap on this machine")
    if name == "bwrap":  # its probe is what failed under a private folder: no skipping that
        return BwrapBackend(there, cache / "bwrap")
    try:
        return DockerBackend(there)
    except BackendUnavailable as err:
        if os.environ.get("CI"):
            pytest.fail(str(err))
        pytest.skip(str(err))


@pytest.mark.integration
@pytest.mark.parametrize("name", ["bwrap", "docker"])
async def test_a_job_runs_from_under_a_private_folder(
    name: str, runtime: Runtime, private: Path, views: Path
) -> None:
    """Requirements install into, and a job imports from and runs code in, folders
    under a 0700 folder; no bind or mount point is left."""
    backend = backend_in(name, runtime, private)
    try:
        requirements = private / "repo" / "requirements.txt"
        requirements.parent.mkdir()
        requirements.write_text("six==1.17.0\n")
        target = private / "lab-data" / "cache" / "requirements" / "six"
        await backend.install(requirements, target)
        code = private / "repo"
        (code / "controller.py").write_text(
            "import six, pathlib\nprint(six.__version__, pathlib.Path('data.txt').read_text())\n"
        )
        (code / "data.txt").write_text("from a private folder")
        job = Job(
            command=["python", "controller.py"],
            code=code,
            bridge_socket=None,
            python_paths=[target],
            limits=Limits(wall=60),
        )
        running = await backend.start(job)
        ended = await running.wait()
        assert_nothing_left(backend, running)
        assert ended.code == 0, ended.stderr
        assert ended.stdout == b"1.17.0 from a private folder\n"
    finally:
        if isinstance(backend, DockerBackend):
            backend.close()
    if name == "bwrap":  # it made mount points, and removed them
        assert views.is_dir()
    assert views_left(views) == set()


def test_a_path_out_of_reach_is_bound_and_mapped(private: Path) -> None:
    """A path a job's uid cannot reach gets a view it can; reachable paths stay as they are."""
    (private / "runtime" / "etc").mkdir(parents=True)
    reachable = Path(tempfile.gettempdir())
    views = Views.make([private / "runtime", private / "runtime" / "etc", reachable], UIDS[0])
    try:
        assert [source for source, _ in views.binds] == [private / "runtime"]
        assert views.folder is not None and views.folder.stat().st_mode & 0o777 == 0o755
        assert views.path(private / "runtime" / "etc" / "passwd") == str(
            views.folder / "0" / "etc" / "passwd"
        )
        assert views.path(reachable) == str(reachable)
        assert "--reuid=64100" in views.command(["bwrap"], UIDS[0])
    finally:
        views.remove()
    assert views.folder is None


def test_without_the_tools_to_bind_the_refusal_says_what_to_change(
    private: Path, views: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """No util-linux to bind with: one line naming the folder and what to change."""
    monkeypatch.setenv("PATH", "/nonexistent")
    with pytest.raises(SandboxError) as raised:
        Views.make([private / "code"], UIDS[0])
    message = str(raised.value)
    assert "\n" not in message
    assert f"{private} is not searchable by others; chmod o+x {private}" in message
    assert "keep the lab's data folder elsewhere" in message
    assert views_left(views) == set()


@pytest.mark.integration
def test_two_labs_never_lease_the_same_uid(runtime: Runtime, workdir: Path) -> None:
    """Backends with different state folders (two labs, two --data) lease apart: each
    kills what runs as the uid it leases, so sharing one would kill the other's job."""
    if shutil.which("bwrap") is None:
        pytest.skip("no bwrap on this machine")
    one = BwrapBackend(runtime, workdir / "lab-one")
    two = BwrapBackend(runtime, workdir / "lab-two")
    first = one.uids.lease() if one.uids else None
    second = two.uids.lease() if two.uids else None
    assert first is not None and second is not None
    try:
        assert first.uid != second.uid
    finally:
        first.release()
        second.release()
