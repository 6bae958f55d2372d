"""The build steps: a repository's requirements, as wheels, into a folder jobs then import
from; npm packages; and what each step may reach (the configured registry alone)."""

from __future__ import annotations

import asyncio
import json
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path

import pytest

from sandbox.api import Backend, Exit, InstallError
from sandbox.install import (
    PROXY_URL,
    npm_default_registry,
    npm_step,
    pip_defaults,
    pip_step,
    run_step,
)
from sandbox.jobs import Plan
from sandbox.proxy import Destination
from sandbox.runtime import NPM_CLI, PIP_PATH, Runtime
from tests.faults.slow import PackageIndex
from tests.sandbox.conftest import Controllers, Upstream

pytestmark = [pytest.mark.integration, pytest.mark.timeout(300)]


def requirements(workdir: Path, text: str) -> Path:
    folder = workdir / f"reqs-{os.urandom(4).hex()}"
    folder.mkdir(mode=0o700)  # the backend stages it where the sandbox can read it
    path = folder / "requirements.txt"
    path.write_text(text)
    path.chmod(0o600)
    return path


async def test_a_wheel_installs_and_imports(
    backend: Backend, controllers: Controllers, workdir: Path
) -> None:
    """A pure-Python wheel installs into the target, owned by the lab, and a job imports it."""
    target = workdir / f"target-{os.urandom(4).hex()}"
    await backend.install(requirements(workdir, "six==1.17.0\n"), target)
    assert (target / "six.py").is_file()
    assert {p.stat().st_uid for p in [target, *target.rglob("*")]} == {os.geteuid()}
    ended = await controllers.run(
        """
        import six
        print(six.__version__, six.__file__)
        """,
        python_paths=[target],
    )
    assert ended.code == 0, ended.stderr
    assert ended.stdout == b"1.17.0 /mnt/python/0/six.py\n"


async def test_a_missing_package_fails_with_pips_reason(backend: Backend, workdir: Path) -> None:
    """A package that does not exist fails with InstallError and the end of pip's output."""
    target = workdir / f"target-{os.urandom(4).hex()}"
    with pytest.raises(InstallError) as raised:
        await backend.install(requirements(workdir, "labd-no-such-package-7f3a9c==1.0\n"), target)
    assert "labd-no-such-package-7f3a9c" in raised.value.reason
    assert "No matching distribution" in raised.value.log


@pytest.mark.parametrize("line", ["-e .", "--no-binary :all:", "--editable=git+https://x/y"])
async def test_options_that_would_build_are_refused(
    backend: Backend, workdir: Path, line: str
) -> None:
    """Requirements that would build from source (and so run code) are refused up front."""
    with pytest.raises(InstallError, match="not allowed"):
        await backend.install(requirements(workdir, f"six\n{line}\n"), workdir / "never")
    assert not (workdir / "never").exists()


async def test_a_linked_or_binary_requirements_file_is_refused(
    backend: Backend, workdir: Path
) -> None:
    """The install step reads the file itself, never through a link, and only as text."""
    secret = requirements(workdir, "six==1.17.0  # the host's file\n")
    link = secret.with_name("linked.txt")
    link.symlink_to(secret)
    with pytest.raises(InstallError, match="it is a symbolic link"):
        await backend.install(link, workdir / "never")
    binary = requirements(workdir, "")
    binary.write_bytes(b"\xff\xfesix\n")
    with pytest.raises(InstallError, match="not UTF-8 text"):
        await backend.install(binary, workdir / "never")
    assert not (workdir / "never").exists()


# -- the build step's network: the configured registry, through the lab's proxy alone ----------

MS_PACKAGE = {"name": "p", "private": True, "dependencies": {"ms": "2.1.3"}}
MS_LOCK = {
    "name": "p",
    "lockfileVersion": 3,
    "requires": True,
    "packages": {
        "": {"name": "p", "dependencies": {"ms": "2.1.3"}},
        "node_modules/ms": {
            "version": "2.1.3",
            "integrity": "sha512-6FlzubTLZG3J2a/NVCAleEhjzq5oxgHyaCU9yYXvcLsvoVaHJq/s5xXI6/"
            "XXP6tz7R9xAOtHnSO/tXtF3WRTlA==",
        },
    },
}


def node_package(workdir: Path) -> tuple[Path, Path]:
    folder = workdir / f"node-{os.urandom(4).hex()}"
    folder.mkdir(mode=0o755)
    (folder / "package.json").write_text(json.dumps(MS_PACKAGE))
    (folder / "package-lock.json").write_text(json.dumps(MS_LOCK))
    return folder / "package.json", folder / "package-lock.json"


@pytest.fixture
def package_index() -> Iterator[PackageIndex]:
    """A package index on the lab machine's 127.0.0.1, answering at once."""
    server = PackageIndex()
    server.release.set()
    yield server
    server.shutdown()
    server.server_close()


async def test_an_index_the_operator_put_on_the_labs_loopback_is_reached(
    backend: Backend,
    controllers: Controllers,
    workdir: Path,
    package_index: PackageIndex,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """PIP_INDEX_URL on the host's 127.0.0.1 is the configured index: the build step, whose
    sandbox has no network of its own, reaches it through the lab's proxy (Docker too)."""
    monkeypatch.setenv("PIP_INDEX_URL", package_index.url)
    target = workdir / f"target-{os.urandom(4).hex()}"
    await backend.install(requirements(workdir, "tinypkg==1.0\n"), target)
    assert package_index.asked.is_set()
    ended = await controllers.run("import tinypkg; print(tinypkg.VALUE)", python_paths=[target])
    assert ended.stdout == b"7\n", ended.stderr


async def test_npm_reaches_the_registry_through_the_hosts_own_proxy(
    backend: Backend,
    runtime: Runtime,
    workdir: Path,
    upstream: Upstream,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Where the host goes through a proxy of its own, the build step's proxy chains to it:
    one CONNECT to the configured registry, and the package installs."""
    monkeypatch.setenv("HTTPS_PROXY", f"http://127.0.0.1:{upstream.port}")
    assert runtime.node is not None
    registry = Destination.of_url(
        npm_default_registry(runtime.node, str(runtime.root / NPM_CLI.lstrip("/")))
    )
    target = workdir / f"target-{os.urandom(4).hex()}"
    await backend.install_node(*node_package(workdir), target)
    assert (target / "node_modules" / "ms" / "package.json").is_file()
    assert {head.split(b" ")[1].decode() for head in upstream.heads} == {str(registry)}
    assert all(head.startswith(b"CONNECT ") for head in upstream.heads)


def test_pip_is_given_its_configured_indexes_and_nothing_else(
    runtime: Runtime, workdir: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The pip step may reach the hosts of PIP_INDEX_URL and PIP_EXTRA_INDEX_URL (a file://
    index gives none); the host's proxy settings are not passed on, the lab's replace them."""
    monkeypatch.setenv("PIP_INDEX_URL", "http://127.0.0.1:8631/simple")
    monkeypatch.setenv("PIP_EXTRA_INDEX_URL", "https://mirror.example/simple file:///opt/x")
    monkeypatch.setenv("HTTPS_PROXY", "http://corporate.example:3128")
    monkeypatch.setenv("NO_PROXY", "127.0.0.1,localhost")
    step = pip_step(runtime, requirements(workdir, "six\n"), workdir / "never")
    assert step.allowed == {
        Destination("127.0.0.1", 8631),
        Destination("mirror.example", 443),
    }
    assert step.env["PIP_INDEX_URL"] == "http://127.0.0.1:8631/simple"
    assert step.env["PIP_PROXY"] == step.env["HTTPS_PROXY"] == PROXY_URL
    assert "NO_PROXY" not in step.env and "no_proxy" not in step.env


def test_pip_without_an_index_reaches_its_default_index_and_its_files(
    runtime: Runtime, workdir: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """With no index configured, the pip step reaches pip's own default index and the host
    that index serves its files from, as the runtime's pip names them, and nothing else."""
    monkeypatch.delenv("PIP_INDEX_URL", raising=False)
    monkeypatch.delenv("PIP_EXTRA_INDEX_URL", raising=False)
    step = pip_step(runtime, requirements(workdir, "six\n"), workdir / "never")
    index, files = pip_defaults(runtime.python, str(runtime.root / PIP_PATH.lstrip("/")))
    assert index.startswith("https://") and "." in files
    assert step.allowed == {Destination.of_url(index), Destination(files, 443)}


@pytest.mark.parametrize("variable", ["npm_config_registry", "NPM_CONFIG_REGISTRY"])
def test_npm_is_given_its_configured_registry_and_nothing_else(
    runtime: Runtime, workdir: Path, monkeypatch: pytest.MonkeyPatch, variable: str
) -> None:
    """The npm step may reach the configured registry alone, which npm is told itself;
    npm's proxy settings are the lab's."""
    for name in ("npm_config_registry", "NPM_CONFIG_REGISTRY"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv(variable, "https://npm.example:8443/")
    step = npm_step(runtime, workdir)
    assert step.allowed == {Destination("npm.example", 8443)}
    assert step.env["npm_config_registry"] == "https://npm.example:8443/"
    assert step.env["npm_config_proxy"] == step.env["npm_config_https_proxy"] == PROXY_URL


async def test_a_step_is_served_its_proxy_while_it_runs_and_told_what_it_was_refused(
    runtime: Runtime, workdir: Path, monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    """The step's proxy listens (even where the temporary folder's path is too long for a
    socket) while the step runs and is gone after; a step that failed after a refusal
    fails naming what it could not reach."""
    long = tmp_path / ("x" * 80)
    long.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(long))
    step = npm_step(runtime, workdir)
    seen: list[Path] = []

    async def run(plan: Plan) -> Exit:
        assert plan.proxy_socket is not None and plan.proxy_socket.is_socket()
        seen.append(plan.proxy_socket)
        reader, writer = await asyncio.open_unix_connection(str(plan.proxy_socket))
        writer.write(b"CONNECT 127.0.0.1:22 HTTP/1.1\r\n\r\n")
        assert (await reader.read()).startswith(b"HTTP/1.1 403 Forbidden\r\n")
        writer.close()
        return Exit(code=1, stderr=b"npm error 403 Forbidden - GET https://127.0.0.1:22/x\n")

    with pytest.raises(InstallError) as raised:
        await run_step(step, run)
    assert raised.value.reason == (
        "npm could not reach 127.0.0.1:22: the build step reaches only the configured registry"
    )
    assert not seen[0].exists() and not seen[0].parent.exists()
