"""The build step's network (issue 32): it reaches the configured registry and nothing else.

The attack: a repository's package-lock.json whose ``resolved`` URL points at a listener
on the lab machine itself had its tarball fetched by ``npm ci`` in the build step, which
ran with the host's network (bubblewrap's ``--share-net``: the machine's loopback and
every address of it; Docker's default bridge: the machine's address on it). A
requirements file naming a wheel by such a URL did the same through pip. Here the
listener is a real HTTP server serving a real package (a .tgz with its correct integrity
hash, a wheel), so an install that reaches it succeeds: the build step must fail
instead, the listener must see no request, and the trial's error must say what could
not be reached. Each case runs in both sandboxes, with the listener on the loopback and
on another address of the machine.
"""

from __future__ import annotations

import asyncio
import base64
import hashlib
import io
import json
import socket
import tarfile
import threading
from collections.abc import Callable, Iterator
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any, ClassVar

import psutil
import pytest

from repository.trial import Order, Outcome
from sandbox.api import PROXY_PORT, Backend
from sandbox.docker import DockerBackend
from sandbox.install import INSTALL_LIMITS
from sandbox.proxy import ProxyLimits
from scheduler.runner import RunOptions, TrialResult, run_trial
from tests.faults.slow import tiny_wheel

pytestmark = [pytest.mark.integration, pytest.mark.timeout(300)]

CONTROLLER_JS = 'import "evil";\nconsole.log("the evil package was installed");\n'
CONTROLLER_PY = 'import tinypkg\nprint("tinypkg was installed", tinypkg.VALUE)\n'


def evil_tarball() -> bytes:
    """An npm package tarball, ``evil`` 1.0.0, as a registry serves one."""
    files = {
        "package/package.json": json.dumps({"name": "evil", "version": "1.0.0", "main": "i.js"}),
        "package/i.js": "module.exports = 'fetched from the lab machine';\n",
    }
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w:gz") as tar:
        for name, text in files.items():
            data = text.encode()
            info = tarfile.TarInfo(name)
            info.size, info.mode = len(data), 0o644
            tar.addfile(info, io.BytesIO(data))
    return buffer.getvalue()


class Listener(ThreadingHTTPServer):
    """An HTTP server on one of the lab machine's own addresses, serving ``files`` and
    recording every request it is sent."""

    daemon_threads = True

    def __init__(self, address: str, files: dict[str, bytes]) -> None:
        super().__init__((address, 0), _Handler)
        self.files = files
        self.requests: list[str] = []
        self._thread = threading.Thread(target=self.serve_forever, daemon=True)
        self._thread.start()

    def url(self, path: str) -> str:
        return f"http://{self.server_address[0]}:{self.server_address[1]}{path}"

    def stop(self) -> None:
        self.shutdown()
        self.server_close()
        self._thread.join()


class _Handler(BaseHTTPRequestHandler):
    server: Listener
    protocol_version: ClassVar[str] = "HTTP/1.0"

    def do_GET(self) -> None:
        self.server.requests.append(self.path)
        body = self.server.files.get(self.path)
        if body is None:
            self.send_error(404)
            return
        self.send_response(200)
        self.send_header("Content-Type", "application/octet-stream")
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    def log_message(self, format: str, *args: object) -> None:
        pass


def lab_address(backend: Backend, where: str) -> str:
    """One of the lab machine's own addresses: its loopback, or one the sandbox would
    reach through the host's network (under Docker, its address on the engine's default
    bridge, a container's gateway; under bubblewrap, any other address of the machine)."""
    if where == "loopback":
        return "127.0.0.1"
    interfaces = psutil.net_if_addrs()
    if isinstance(backend, DockerBackend):
        options = backend.client.networks.get("bridge").attrs.get("Options") or {}
        names = [options.get("com.docker.network.bridge.name", "docker0")]
    else:
        names = sorted(interfaces)
    for name in names:
        for address in interfaces.get(name, []):
            if address.family == socket.AF_INET and not address.address.startswith("127."):
                return str(address.address)
    raise AssertionError(f"no IPv4 address of this machine on {names}")


@pytest.fixture(params=["loopback", "host-address"])
def listener(request: pytest.FixtureRequest, backend: Backend) -> Iterator[Listener]:
    """A listener on the lab machine, serving the evil package and tinypkg's wheel."""
    wheel_name, wheel = tiny_wheel()
    files = {"/evil/-/evil-1.0.0.tgz": evil_tarball(), f"/{wheel_name}": wheel}
    server = Listener(lab_address(backend, request.param), files)
    yield server
    server.stop()


def repository(folder: Path, files: dict[str, str]) -> Path:
    folder.mkdir()
    for name, text in files.items():
        (folder / name).write_text(text)
    for path in [folder, *folder.iterdir()]:
        path.chmod(0o755 if path.is_dir() else 0o644)
    return folder


def npm_repository(folder: Path, listener: Listener) -> Path:
    """A JavaScript controller whose lock file fetches ``evil`` from the listener."""
    tarball = listener.files["/evil/-/evil-1.0.0.tgz"]
    integrity = "sha512-" + base64.b64encode(hashlib.sha512(tarball).digest()).decode()
    package = {"name": "victim", "private": True, "dependencies": {"evil": "1.0.0"}}
    lock = {
        "name": "victim",
        "lockfileVersion": 3,
        "requires": True,
        "packages": {
            "": {"name": "victim", "dependencies": {"evil": "1.0.0"}},
            "node_modules/evil": {
                "version": "1.0.0",
                "resolved": listener.url("/evil/-/evil-1.0.0.tgz"),
                "integrity": integrity,
            },
        },
    }
    toml = '[controller]\ncommand = ["node", "c.mjs"]\ntask = "icreate-maze"\n'
    files = {
        "lab.toml": toml,
        "c.mjs": CONTROLLER_JS,
        "package.json": json.dumps(package),
        "package-lock.json": json.dumps(lock),
    }
    return repository(folder, files)


def pip_repository(folder: Path, listener: Listener) -> Path:
    """A Python controller whose requirements name tinypkg's wheel on the listener."""
    wheel_name = next(name for name in listener.files if name.endswith(".whl"))
    toml = '[controller]\ncommand = ["python", "c.py"]\ntask = "icreate-maze"\n'
    files = {
        "lab.toml": toml + 'requirements = "requirements.txt"\n',
        "c.py": CONTROLLER_PY,
        "requirements.txt": f"tinypkg @ {listener.url(wheel_name)}\n",
    }
    return repository(folder, files)


def run(backend: Backend, host: Any, tmp_path: Path, source: Path) -> TrialResult:
    order = Order(repository=str(source), params={"time_limit": 1})
    return asyncio.run(
        run_trial(
            order,
            backend=backend,
            host=host,
            out=tmp_path / "out",
            cache=tmp_path / "cache",  # the trial's own: nothing installed earlier
            options=RunOptions(),
        )
    )


def test_npm_ci_cannot_fetch_from_the_lab_machine(
    backend: Backend, host: Any, tmp_path: Path, listener: Listener
) -> None:
    """A lock file whose tarball lies on the lab machine: npm ci fails, the listener sees
    no request, and the trial's error says the build step could not reach it."""
    source = npm_repository(tmp_path / "repo", listener)
    result = run(backend, host, tmp_path, source)
    assert listener.requests == [], "the build step fetched from the lab machine"
    assert result.outcome is Outcome.ERROR, result.reason
    address, port = listener.server_address[:2]
    assert result.reason.startswith(f"npm packages: npm could not reach http://{address}:{port}/")
    assert "the build step reaches only the configured registry" in result.reason
    assert not list((tmp_path / "cache").glob("node/*"))


def test_pip_cannot_fetch_from_the_lab_machine(
    backend: Backend, host: Any, tmp_path: Path, listener: Listener
) -> None:
    """Requirements naming a wheel on the lab machine: pip fails, the listener sees no
    request, and the trial's error says the build step could not reach it."""
    source = pip_repository(tmp_path / "repo", listener)
    result = run(backend, host, tmp_path, source)
    assert listener.requests == [], "the build step fetched from the lab machine"
    assert result.outcome is Outcome.ERROR, result.reason
    address, port = listener.server_address[:2]
    assert result.reason.startswith(f"requirements: pip could not reach http://{address}:{port}/")
    assert "the build step reaches only the configured package index" in result.reason


DOCS = Path(__file__).resolve().parents[2] / "docs"
PROXY = ProxyLimits()
# Each figure docs/trials.md states of the build step's network, and the code's default.
FIGURES = [
    ("with larger limits (2 GiB of memory, 15 minutes)",
     lambda: (INSTALL_LIMITS.memory, INSTALL_LIMITS.wall), (2048 * 1024 * 1024, 900)),
    ("relayed by its first process to `127.0.0.1:3128`", lambda: PROXY_PORT, 3128),
    ("The proxy holds at most 32 connections", lambda: PROXY.connections, 32),
    ("gives a request 30 s to arrive and a destination 30 s to answer",
     lambda: (PROXY.head_seconds, PROXY.connect_seconds), (30, 30)),
    ("closes a connection silent for 120 s", lambda: PROXY.idle_seconds, 120),
]  # fmt: skip


@pytest.mark.parametrize(("sentence", "value", "stated"), FIGURES, ids=[f[0] for f in FIGURES])
def test_the_docs_state_the_build_steps_figures(
    sentence: str, value: Callable[[], object], stated: object
) -> None:
    """docs/trials.md says each figure of the build step's network as the code has it."""
    text = " ".join((DOCS / "trials.md").read_text().split())
    assert sentence in text, f"docs/trials.md no longer says {sentence!r}"
    assert value() == stated
