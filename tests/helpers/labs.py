"""Whole labs for the tests: ``labd serve``'s ``Lab`` in process, configured in one place.

``lab_config`` says what a test's lab has (live robots, the archive, workers on the
session's runtime); ``running`` starts it on its own event loop thread
(``ServerThread``) and stops it after. Tests that need a lab as another
process use ``tests.faults.conftest.Served`` instead.
"""

from __future__ import annotations

import asyncio
import threading
from collections.abc import Callable, Iterator
from concurrent.futures import Future
from contextlib import contextmanager
from pathlib import Path
from typing import Any, TypeVar

from labd.config import BridgeConfig, RobotConfig
from labd.lab import Lab, LabConfig
from labd.service import ServiceConfig
from scheduler.fetch import FetchPolicy
from tests.helpers.sandboxes import make_backend

T = TypeVar("T")


class ServerThread:
    """A real ``Lab`` (bridge on 127.0.0.1, port 0) on its own event loop thread."""

    def __init__(self, config: LabConfig, **lab_kwargs: Any) -> None:
        self.loop = asyncio.new_event_loop()
        self.lab: Lab | None = None
        self._config = config
        self._kwargs = lab_kwargs
        self._thread = threading.Thread(target=self.loop.run_forever, daemon=True)

    def start(self) -> ServerThread:
        self._thread.start()

        async def boot() -> Lab:
            lab = Lab(self._config, **self._kwargs)
            await lab.start()
            return lab

        self.lab = self.run(boot())
        return self

    def run(self, coro: Any, timeout: float = 30) -> Any:
        return asyncio.run_coroutine_threadsafe(coro, self.loop).result(timeout)

    def call(self, fn: Callable[[], T], timeout: float = 30) -> T:
        """Run ``fn`` on the server's loop (where the graph lives) and return its result."""
        done: Future[T] = Future()

        def target() -> None:
            try:
                done.set_result(fn())
            except BaseException as err:  # handed to the test thread
                done.set_exception(err)

        self.loop.call_soon_threadsafe(target)
        return done.result(timeout)

    def wait_until(self, predicate: Callable[[], bool], timeout: float = 10) -> None:
        """Block until ``predicate`` (checked on the server's loop) holds, or fail."""
        done = threading.Event()

        def poll() -> None:
            if predicate():
                done.set()
            else:
                self.loop.call_later(0.005, poll)

        self.loop.call_soon_threadsafe(poll)
        assert done.wait(timeout), f"condition not met within {timeout} s"

    @property
    def port(self) -> int:
        assert self.lab is not None
        return self.lab.bridge.port

    @property
    def url(self) -> str:
        assert self.lab is not None
        return self.lab.bridge.url()

    def stop(self) -> None:
        if self.lab is not None:
            self.run(self.lab.close())
        self.loop.call_soon_threadsafe(self.loop.stop)
        self._thread.join(10)
        self.loop.close()

    def http_url(self, path: str = "") -> str:
        """The lab's HTTP address, and ``path`` on it."""
        assert self.lab is not None and self.lab.http is not None
        return self.lab.http.url() + path


MAZE = RobotConfig("icreate-1", "icreate-maze")
PR2 = RobotConfig("pr2-1", "pr2-table")


def shared_cache(data: Path, cache: Path) -> None:
    """The session's controller runtime in ``data``'s cache, rather than a cold build."""
    (data / "cache").mkdir(parents=True, exist_ok=True)
    for runtime in cache.glob("runtime-*"):
        link = data / "cache" / runtime.name
        if not link.exists():
            link.symlink_to(runtime)


def lab_config(
    data: Path,
    robots: tuple[RobotConfig, ...] = (MAZE,),
    *,
    workers: int = 0,
    cache: Path | None = None,
    bridge: BridgeConfig | None = None,
    service: dict[str, Any] | None = None,
    **lab: Any,
) -> LabConfig:
    """A lab on loopback and free ports, its archive in ``data``, ``robots`` live (the
    playground only when there is no robot); with ``workers``, that many bubblewrap workers on the session's runtime
    (``cache``) that take local repositories. ``service`` and ``lab`` set the rest. Videos
    are rendered when asked for: a test that wants one asks (the background's renders
    would only take CPU from the tests beside it)."""
    more: dict[str, Any] = dict(service or {})
    more.setdefault("videos", "asked")
    if workers:
        if cache is None:
            raise ValueError("workers run controllers: give the session's runtime cache")
        make_backend("bwrap", cache)  # built, or skipped (failed under CI) if bwrap is missing
        shared_cache(data, cache)
        more.setdefault("sandbox", "bwrap")
        more.setdefault("fetch", FetchPolicy(schemes=frozenset({"file"})))
    lab.setdefault("playground", not robots)  # a bridge needs a graph: without robots, this one
    return LabConfig(
        data=data,
        bridge=bridge or BridgeConfig(port=0),
        robots=robots,
        http_port=0,
        service=ServiceConfig(data=data, workers=workers, **more),
        **lab,
    )


@contextmanager
def running(config: LabConfig) -> Iterator[Any]:
    """The lab of ``config``, started on its own thread (a ``ServerThread``), then stopped."""
    server = ServerThread(config).start()
    try:
        yield server
    finally:
        server.stop()
