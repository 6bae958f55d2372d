"""A machine with neither sandbox: one error, at once, naming both and what to install.

Nothing here is faked: bwrap is missing because PATH holds only git (which the lab imports
with GitPython), and no Docker engine answers because ``DOCKER_HOST`` names a socket that
is not there, or one that refuses. The chooser asks both before it builds the runtime, so
the error comes before a minute of building, and the cache stays empty.
"""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

import sandbox
from sandbox.docker import connect

ROOT = Path(__file__).resolve().parents[2]
MAZE = ROOT / "controllers" / "examples" / "icreate-maze"


@pytest.fixture
def no_bwrap(tmp_path: Path) -> Path:
    """A PATH folder with git alone: no bwrap, no prlimit, no engine's client."""
    folder = tmp_path / "bin"
    folder.mkdir()
    git = shutil.which("git")
    assert git is not None, "the lab needs git"
    (folder / "git").symlink_to(git)
    return folder


@pytest.fixture
def nothing(monkeypatch: pytest.MonkeyPatch, no_bwrap: Path) -> Iterator[dict[str, str]]:
    """This process's environment (and a child's) with neither sandbox."""
    env = {"PATH": str(no_bwrap), "DOCKER_HOST": "unix:///nonexistent"}
    for key, value in env.items():
        monkeypatch.setenv(key, value)
    yield env


def assert_says_both(message: str) -> None:
    assert "no Docker engine answers at unix:///nonexistent (no such file or directory)" in (
        message
    )
    assert "no bwrap on PATH" in message
    assert "apt-get install bubblewrap" in message
    assert "apt-get install docker.io, then systemctl start docker" in message
    assert "--sandbox docker|bwrap" in message
    assert "\n" not in message


def test_with_neither_the_chooser_names_both_and_what_to_install(
    nothing: dict[str, str], tmp_path: Path
) -> None:
    """backend(None) with no engine and no bwrap raises one NoSandbox (a
    BackendUnavailable, as callers catch) saying why each failed and what to install on
    Debian, before building anything."""
    cache = tmp_path / "cache"
    with pytest.raises(sandbox.NoSandbox) as raised:
        sandbox.backend(None, cache)
    assert isinstance(raised.value, sandbox.BackendUnavailable)
    assert [err.backend for err in raised.value.tried] == ["docker", "bwrap"]
    assert_says_both(str(raised.value))
    assert not cache.exists() or not any(cache.iterdir())


def test_a_named_backend_says_what_to_install(nothing: dict[str, str], tmp_path: Path) -> None:
    """--sandbox bwrap without bwrap names Debian's package; --sandbox docker without an
    engine names the engine's package and how to start it; neither builds anything."""
    with pytest.raises(sandbox.BackendUnavailable) as bwrap:
        sandbox.backend("bwrap", tmp_path / "cache")
    assert str(bwrap.value) == (
        "the bwrap sandbox is not available: no bwrap on PATH"
        " (on Debian: apt-get install bubblewrap)"
    )
    with pytest.raises(sandbox.BackendUnavailable) as docker:
        sandbox.backend("docker", tmp_path / "cache")
    assert str(docker.value) == (
        "the docker sandbox is not available: no Docker engine answers at"
        " unix:///nonexistent (no such file or directory)"
        " (on Debian: apt-get install docker.io, then systemctl start docker)"
    )
    assert not (tmp_path / "cache").exists()


def test_an_engine_that_refuses_is_said_to_need_starting(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    """A socket that is there but refuses (an engine installed, not running) is said in
    two words, with the command that starts the engine."""
    path = tmp_path / "docker.sock"
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as bound:  # bound, not listening
        bound.bind(str(path))
        monkeypatch.setenv("DOCKER_HOST", f"unix://{path}")
        with pytest.raises(sandbox.BackendUnavailable) as raised:
            connect()
    assert raised.value.reason == f"no Docker engine answers at unix://{path} (connection refused)"
    assert raised.value.hint == "systemctl start docker"


@pytest.mark.integration
@pytest.mark.parametrize(
    "argv",
    [
        ["run", str(MAZE), "--task", "icreate-maze"],
        ["worker", "--server", "http://127.0.0.1:9", "--token", "t"],
        ["serve", "--http-port", "0", "--bridge-port", "0", "--no-robots", "--workers", "1"],
    ],
    ids=["run", "worker", "serve"],
)
def test_the_commands_print_the_one_line(
    nothing: dict[str, str], tmp_path: Path, argv: list[str]
) -> None:
    """labd run, labd worker and labd serve (whose workers need a sandbox) on a machine
    with neither sandbox exit 2 with that one line, no traceback."""
    done = subprocess.run(
        [sys.executable, "-m", "labd", *argv, "--data", str(tmp_path / "data")],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
        env={**os.environ, **nothing},
    )
    assert done.returncode == 2, done.stderr
    line = done.stderr.strip()
    assert line.startswith(f"labd {argv[0]}: no sandbox can run controllers here: "), line
    assert_says_both(line)
