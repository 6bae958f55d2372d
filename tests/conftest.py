"""Shared fixtures: the type registry, graphs, sessions, a real bridge server, the
databases and an index on a clock the test moves, the sandboxes (one runtime for the
session) and the lab's side of a trial. README.md lists the fixtures' names."""

from __future__ import annotations

import contextlib
import os
import secrets
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, TypeVar

import orjson
import pytest
import sqlalchemy as sa

from labd.bridge.ops import CAPABILITIES
from labd.bridge.rosapi import Rosapi
from labd.bridge.session import Session
from labd.config import BridgeConfig
from labd.graph.graph import Graph
from labd.graph.types import TypeRegistry
from labd.lab import LabConfig
from labd.trial import LabHost
from repository.index import Index
from repository.index import connect as engine
from sandbox.api import Backend
from sandbox.docker import DockerBackend
from tests.fakes import ManualTimers, RecordingTransport, WallClock, drain
from tests.helpers.labs import ServerThread
from tests.helpers.sandboxes import BACKENDS, make_backend, runtime_cache

T = TypeVar("T")


_SPENT: dict[str, float] = {}  # seconds by test file (setup, call and teardown)
_BUSY: dict[str, float] = {}  # seconds by xdist worker


def pytest_runtest_logreport(report: pytest.TestReport) -> None:
    """Add up where a run's time goes (on xdist's controller, its workers' reports)."""
    path = report.nodeid.split("::", 1)[0]
    _SPENT[path] = _SPENT.get(path, 0.0) + report.duration
    node = getattr(report, "node", None)
    worker = getattr(getattr(node, "gateway", None), "id", "main")
    _BUSY[worker] = _BUSY.get(worker, 0.0) + report.duration


@pytest.hookimpl(trylast=True)
def pytest_terminal_summary(terminalreporter: Any) -> None:
    """A few lines, just above the short summary, that say where the time went: the
    slowest files and each worker's busy time (a slow CI run shows its cause in its tail)."""
    if not _SPENT:
        return
    slowest = sorted(_SPENT.items(), key=lambda kv: -kv[1])[:8]
    terminalreporter.write_sep("=", "where the time went")
    terminalreporter.write_line(
        "slowest files: "
        + ", ".join(f"{path.removeprefix('tests/')} {s:.0f} s" for path, s in slowest)
    )
    terminalreporter.write_line(
        f"all tests: {sum(_SPENT.values()):.0f} s; busy by worker: "
        + ", ".join(f"{w} {s:.0f} s" for w, s in sorted(_BUSY.items()))
    )


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Tests that load the machine (crowds, floods) run one at a time on one worker of a
    parallel run (pytest-xdist's ``--dist loadgroup``), so no two of them share the cores."""
    for item in items:
        if item.get_closest_marker("rates"):
            item.add_marker(pytest.mark.xdist_group("rates"))


@pytest.fixture(scope="session")
def registry() -> TypeRegistry:
    return TypeRegistry.default()


@pytest.fixture
def timers() -> ManualTimers:
    return ManualTimers()


@pytest.fixture
def graph(registry: TypeRegistry, timers: ManualTimers) -> Graph:
    """A graph whose time is the manual clock (so stamps are predictable)."""
    g = Graph(registry, name="test", clock=lambda: int(timers.now * 1e9))
    Rosapi(g, ("/protected",))
    return g


class Client:
    """A session driven with strings, as a test sees one client."""

    def __init__(self, session: Session, transport: RecordingTransport) -> None:
        self.session = session
        self.transport = transport

    def send(self, frame: dict[str, Any] | str | bytes) -> None:
        self.session.receive(frame if isinstance(frame, str | bytes) else orjson.dumps(frame))

    def frames(self) -> list[Any]:
        return drain(self.session)


@pytest.fixture
def connect(graph: Graph, timers: ManualTimers) -> Iterator[Callable[..., Client]]:
    """Make clients of ``graph``: ``connect(config=None, auth_required=False, url_key=None)``."""
    made: list[Session] = []
    ids = iter(range(1, 10_000))

    def make(config: BridgeConfig | None = None, **kwargs: Any) -> Client:
        transport = RecordingTransport()
        session = Session(
            graph,
            config or BridgeConfig(),
            timers,
            transport,
            client_id=next(ids),
            capabilities=CAPABILITIES,
            **kwargs,
        )
        made.append(session)
        return Client(session, transport)

    yield make
    for session in made:
        session.close()


@pytest.fixture
def make_server(tmp_path: Any) -> Iterator[Callable[..., ServerThread]]:
    """Start real servers: ``make_server(bridge=BridgeConfig(...), robots=(...), authorizer=...)``.

    Without ``robots``, the lab hosts only its playground graph (fast to start).
    """
    started: list[ServerThread] = []

    def make(bridge: BridgeConfig | None = None, **lab_kwargs: Any) -> ServerThread:
        lab_kwargs.setdefault("robots", ())
        config = LabConfig(
            data=tmp_path / "lab-data",
            bridge=bridge or BridgeConfig(port=0),
            robots=lab_kwargs.pop("robots"),
        )
        server = ServerThread(config, **lab_kwargs).start()
        started.append(server)
        return server

    yield make
    for server in started:
        server.stop()


@pytest.fixture
def server(make_server: Callable[..., ServerThread]) -> ServerThread:
    """One real lab with default settings on a free port."""
    return make_server()


@pytest.fixture
def sqlite_url(tmp_path: Any) -> str:
    """An empty archive database in SQLite, for tests above the index (the HTTP API)
    whose SQL the repository's and the queue's own tests run on both databases."""
    return f"sqlite:///{tmp_path / 'index.sqlite'}"


@pytest.fixture(params=["sqlite", "postgresql"])
def database_url(request: pytest.FixtureRequest, tmp_path: Any) -> Iterator[str]:
    """An empty archive database: SQLite in tmp_path, or a fresh PostgreSQL database.

    The PostgreSQL server is the one ``.ci/postgres`` starts (``LABD_TEST_POSTGRES_URL``);
    without it these tests skip, except in CI where they fail.
    """
    if request.param == "sqlite":
        yield f"sqlite:///{tmp_path / 'index.sqlite'}"
        return
    with postgres_databases() as fresh:
        yield fresh()


@pytest.fixture
def clock() -> WallClock:
    """The index's clock, at 1,000,000 s until the test moves it (a module whose times
    are dates starts its own ``clock`` there)."""
    return WallClock(1_000_000.0)


@pytest.fixture
def clocked_index(database_url: str, clock: WallClock) -> Iterator[Index]:
    """An empty index on each database whose time is ``clock``, for tests of leases,
    quotas and expiries (``tests/repository``'s ``index`` reads the real time)."""
    index = Index(engine(database_url), clock=clock)
    index.create()
    yield index
    index.close()


@contextlib.contextmanager
def postgres_databases() -> Iterator[Callable[[], str]]:
    """``fresh()``: the URL of a new, empty PostgreSQL database, each call another, all
    dropped at the end. The server is the one ``.ci/postgres`` starts
    (``LABD_TEST_POSTGRES_URL``); without it the test skips, except in CI where it fails."""
    admin_url = os.environ.get("LABD_TEST_POSTGRES_URL")
    if not admin_url:
        if os.environ.get("CI"):
            pytest.fail("LABD_TEST_POSTGRES_URL is not set: .ci/postgres starts a server")
        pytest.skip("no PostgreSQL server (run .ci/postgres and set LABD_TEST_POSTGRES_URL)")
    admin = sa.create_engine(admin_url, isolation_level="AUTOCOMMIT")
    made: list[str] = []

    def fresh() -> str:
        name = f"labd_test_{secrets.token_hex(6)}"
        with admin.connect() as db:
            db.execute(sa.text(f'CREATE DATABASE "{name}"'))
        made.append(name)
        return admin_url.rsplit("/", 1)[0] + "/" + name

    try:
        yield fresh
    finally:
        with admin.connect() as db:
            for name in made:
                db.execute(sa.text(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)'))
        admin.dispose()


@pytest.fixture(scope="session")
def cache(request: pytest.FixtureRequest) -> Path:
    """The runtime cache (pytest's cache folder), shared by every sandbox of the session."""
    return runtime_cache(request.config)


@pytest.fixture(scope="session", params=BACKENDS)
def backend(request: pytest.FixtureRequest, cache: Path) -> Iterator[Backend]:
    """Each sandbox backend in turn, made once per session on the shared runtime."""
    made = make_backend(request.param, cache)
    yield made
    if isinstance(made, DockerBackend):
        made.close()


@pytest.fixture(scope="session")
def host() -> LabHost:
    """The lab's side of a trial."""
    return LabHost()
