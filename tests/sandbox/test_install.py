"""install(): a repository's requirements, as wheels, into a folder jobs then import from."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from sandbox.api import Backend, InstallError
from tests.sandbox.conftest import Controllers

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
