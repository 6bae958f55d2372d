"""The runtime both backends share, the backend chooser, and the shared job logic."""

from __future__ import annotations

import signal
from pathlib import Path

import pytest

import sandbox
from sandbox.api import Backend, InstallError, Job, SandboxError
from sandbox.bwrap import BwrapBackend
from sandbox.docker import DockerBackend
from sandbox.install import check_requirements, npm_step
from sandbox.jobs import KEEP, Stream, decode_status, job_plan
from sandbox.runtime import Runtime, build_runtime, tree_digest

pytestmark = pytest.mark.timeout(600)


@pytest.mark.integration
def test_the_digest_is_the_trees_content(runtime: Runtime) -> None:
    """The runtime's digest is the sha256 of its tree as it is on disk now."""
    assert tree_digest(runtime.root) == runtime.digest


@pytest.mark.integration
def test_both_backends_run_the_same_runtime(backend: Backend, runtime: Runtime) -> None:
    """Every backend reports the digest of the one runtime."""
    assert backend.runtime_digest() == runtime.digest


@pytest.mark.integration
def test_the_runtime_holds_what_controllers_need_and_no_more(runtime: Runtime) -> None:
    """The runtime has Python, its packages, a shell, a minimal /etc; not the host's packages."""
    root = runtime.root
    python = Path(runtime.python)
    assert (root / str(python).lstrip("/")).is_file()
    for alias in ("python", "python3"):
        assert (root / str(python.parent / alias).lstrip("/")).is_symlink()
    assert (root / "bin/sh").exists() and (root / "usr/bin/env").exists()
    assert sorted(p.name for p in (root / "etc").iterdir()) == [
        "group",
        "hosts",
        "nsswitch.conf",
        "passwd",
    ]
    site = root / "opt/labd/site-packages"
    assert {"numpy", "websockets", "roslibpy", "controllers"} <= {p.name for p in site.iterdir()}
    stdlib = root / str(python.parent.parent).lstrip("/") / "lib" / python.name
    assert (stdlib / "os.py").is_file()
    assert not (stdlib / "site-packages").exists()
    assert not list(root.rglob("mujoco*")) and not list(root.rglob("dm_control*"))
    assert (root / "opt/labd/launcher.py").is_file()
    # Node.js (the host has 20 or later) and roslib, found from /code through /node_modules
    assert runtime.node is not None and (root / runtime.node.lstrip("/")).is_file()
    assert runtime.node_version is not None and int(runtime.node_version[1:].split(".")[0]) >= 20
    assert (root / "node_modules/roslib").is_symlink()
    assert (root / "opt/labd/node_modules/roslib/package.json").is_file()
    assert (root / "opt/labd/node_modules/npm/bin/npm-cli.js").is_file()


def test_node_commands_without_node_in_the_runtime_say_so(tmp_path: Path) -> None:
    """A runtime built on a host without Node.js refuses a node command in one line."""
    runtime = Runtime(tmp_path, "0" * 64, "/usr/bin/python3.11", 0, 0.0, node=None)
    job = Job(command=["node", "controller.mjs"], code=tmp_path, bridge_socket=None)
    with pytest.raises(SandboxError, match=r"this lab's sandbox has no Node\.js"):
        job_plan(runtime, job)
    with pytest.raises(InstallError, match=r"this lab's sandbox has no Node\.js"):
        npm_step(runtime, tmp_path)


@pytest.mark.integration
def test_an_existing_runtime_is_reused(runtime: Runtime, cache: Path, extra_packages: list[Path]):
    """Building again from the same inputs returns the runtime already there, at once."""
    again = build_runtime(cache, extra_packages)
    assert (again.root, again.digest, again.build_seconds) == (runtime.root, runtime.digest, 0.0)


@pytest.mark.integration
def test_the_same_inputs_build_the_same_runtime(
    runtime: Runtime, tmp_path: Path, extra_packages: list[Path]
) -> None:
    """A second build from the same inputs, elsewhere, has the same digest, bit for bit."""
    assert build_runtime(tmp_path / "cache", extra_packages).digest == runtime.digest


@pytest.mark.integration
def test_the_chooser_takes_docker_where_an_engine_answers(
    cache: Path, extra_packages: list[Path]
) -> None:
    """backend(None) is Docker when an engine answers; a name picks that backend."""
    chosen = sandbox.backend(None, cache, extra_packages)
    try:
        assert isinstance(chosen, DockerBackend)
    finally:
        if isinstance(chosen, DockerBackend):
            chosen.close()
    assert isinstance(sandbox.backend("bwrap", cache, extra_packages), BwrapBackend)


def test_an_unknown_backend_is_unavailable(tmp_path: Path) -> None:
    """Naming a backend that does not exist says which ones do."""
    with pytest.raises(sandbox.BackendUnavailable, match="docker, bwrap"):
        sandbox.backend("chroot", tmp_path)


@pytest.mark.integration
def test_no_engine_means_docker_is_unavailable(
    runtime: Runtime, monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    """Where no Docker engine answers, DockerBackend is unavailable, saying why."""
    monkeypatch.setenv("DOCKER_HOST", f"unix://{tmp_path}/no-engine.sock")
    with pytest.raises(sandbox.BackendUnavailable) as raised:
        DockerBackend(runtime)
    assert raised.value.backend == "docker"
    assert "no-engine.sock" in raised.value.reason


def test_output_keeps_the_beginning_and_the_end() -> None:
    """A stream keeps its first and last KEEP bytes and says how much it left out."""
    stream = Stream()
    stream.feed(b"a" * KEEP)
    stream.feed(b"b" * 1000)
    stream.feed(b"c" * KEEP)
    value = stream.value()
    assert value.startswith(b"a" * KEEP + b"\n[... 1000 bytes left out by the sandbox ...]\n")
    assert value.endswith(b"c" * KEEP)
    assert stream.total == 2 * KEEP + 1000
    small = Stream()
    small.feed(b"hello ")
    small.feed(b"world")
    assert small.value() == b"hello world"


def test_exit_statuses_decode_as_the_shell_does() -> None:
    """0-128 are codes; 128+N and -N are signal N."""
    assert decode_status(0) == (0, None)
    assert decode_status(3) == (3, None)
    assert decode_status(128 + signal.SIGKILL) == (None, signal.SIGKILL)
    assert decode_status(-signal.SIGTERM) == (None, signal.SIGTERM)
    assert decode_status(255) == (255, None)


@pytest.mark.parametrize(
    ("text", "allowed"),
    [
        ("six==1.17.0\nnumpy>=2  # comment\n", True),
        ("--index-url https://example.org/simple\nsix\n", True),
        ("-e .\n", False),
        ("--editable ./pkg\n", False),
        ("--no-binary=:all:\nsix\n", False),
        ("--no-build-isolation\n", False),
        ("pkg @ https://example.org/pkg-1.0-py3-none-any.whl\n", True),
        ("pkg @ git+https://example.org/pkg.git\n", False),
        ("https://example.org/pkg-1.0.tar.gz\n", False),
        ("./vendored/pkg\n", False),
        ("numpy==2.4.6 ; python_version >= '3.11'\n", True),
    ],
)
def test_requirements_that_would_build_are_refused(text: str, allowed: bool) -> None:
    """Only requirements that pip can meet with wheels pass the check."""
    if allowed:
        check_requirements(text)
    else:
        with pytest.raises(InstallError):
            check_requirements(text)
