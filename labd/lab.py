"""The lab as one object: its graphs, their rosapi nodes, and the bridge serving them.

``labd serve`` builds one; tests build one on port 0. With a service configured it
also runs the archive, the queue's workers and the HTTP API over them.
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import logging
import random
from collections.abc import Coroutine
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from fastapi import FastAPI

from labd.api.server import HttpServer
from labd.api.state import state_of
from labd.authorizer import ref
from labd.bridge.auth import Authorizer, HttpAuthorizer, KeyPolicy
from labd.bridge.rosapi import Rosapi
from labd.bridge.server import BridgeServer
from labd.config import DATA, BridgeConfig, DriveLimits, HttpConfig, RobotConfig
from labd.errors import PortInUse
from labd.graph.graph import Graph
from labd.graph.types import TypeRegistry
from labd.live import Demonstration, Driving, Filings
from labd.service import Service, ServiceConfig
from labd.sim import registry
from labd.sim.robot import LiveRunner, Robot
from labd.station import Station
from labd.web import RobotLink, Site, create_app
from repository.reservations import Reservation

log = logging.getLogger("labd.lab")


def _default_robots() -> tuple[RobotConfig, ...]:
    """A live robot for each task that asks for one (``TaskSpec.robot``)."""
    return tuple(RobotConfig(name, task) for name, task in registry.default_robots())


@dataclass(frozen=True)
class LabConfig:
    """Everything ``labd serve`` needs."""

    data: Path = DATA
    bridge: BridgeConfig = field(default_factory=BridgeConfig)
    robots: tuple[RobotConfig, ...] = field(default_factory=_default_robots)
    # A graph without a robot, where clients reach each other and /rosapi.
    playground: bool = True
    http_port: int = 8080  # the HTTP API
    http: HttpConfig = field(default_factory=HttpConfig)
    # The archive, the queue and its workers; None: only the bridge and its robots.
    service: ServiceConfig | None = None
    # The share of the maze robot's page sessions shown the camera (interface A); the
    # others see the perceptual space (B). The seed makes the draws repeatable (tests).
    interface_ratio: float = 0.5
    interface_seed: int | None = None
    # Live robots behind the lab's reservations: only a slot's key drives (needs service).
    reservations: bool = False
    # With reservations: clients without a key may connect and watch (never drive).
    watchers: bool = True
    # What a drive of a live robot may put in the archive.
    drives: DriveLimits = field(default_factory=DriveLimits)
    # Proxies whose X-Forwarded-For the HTTP API believes (addresses or networks).
    trusted_proxies: tuple[str, ...] = ()


class Lab:
    """Owns everything ``labd serve`` runs; ``start`` and ``close`` it on one event loop,
    the robots' loop: the robots, the bridge, the queue's workers. The HTTP API and the
    pages run on a thread and a loop of their own (``labd.api.server``), and hand what
    touches a live robot to this loop (``Site.robots_loop``)."""

    def __init__(
        self,
        config: LabConfig,
        *,
        types: TypeRegistry | None = None,
        authorizer: Authorizer | None = None,
    ) -> None:
        self.config = config
        self.types = types or TypeRegistry.default()
        self.graphs: dict[str, Graph] = {}
        self.stations: dict[str, Station] = {}
        self.robots: dict[str, Robot] = {}
        protected = config.bridge.protected_prefixes
        for robot in config.robots:
            station = Station(
                self.types,
                robot.name,
                robot.task,
                dict(robot.params),
                robot.seed,
                live=robot.live,
                protected_prefixes=protected,
                node_name="/" + robot.name.replace("-", "_"),
            )
            self.stations[robot.name] = station
            self.graphs[robot.name] = station.graph
            self.robots[robot.name] = station.robot
        self.rosapi: list[Rosapi] = []
        if config.playground:
            self.graphs["playground"] = Graph(self.types, name="playground")
            self.rosapi.append(Rosapi(self.graphs["playground"], protected))
        self._runners: list[asyncio.Task[None]] = []
        self._filings: set[asyncio.Future[int]] = set()
        self.drives: dict[str, Driving] = {}
        self._loop: asyncio.AbstractEventLoop | None = None
        self.service: Service | None = None
        self.http: HttpServer | None = None
        self.site = Site(
            tuple(RobotLink(r.name, r.task, r.live) for r in config.robots),
            bridge_tls=config.bridge.tls_cert is not None,
            interface_ratio=config.interface_ratio,
            rng=random.Random(config.interface_seed),  # noqa: S311 (a study's draw, not a secret)
            reservations=config.reservations,
        )
        self.app: FastAPI | None = None
        if config.service is not None:
            self.service = Service(config.service, self.types)
            self.app = create_app(
                self.service,
                self.site,
                on_submit=self._submitted,
                on_reservation=self._reservation_changed,
            )
            self.http = HttpServer(
                self.app,
                config.bridge.host,
                config.http_port,
                config.http,
                trusted_proxies=config.trusted_proxies,
                tls=_tls(config.bridge),
            )
        self._own_authorizer: HttpAuthorizer | None = None
        policies: dict[str, KeyPolicy] = {}
        if config.reservations:
            if self.service is None or authorizer is not None or config.bridge.authorizer_url:
                raise ValueError("reservations need the archive, and no other authorizer")
            assert self.app is not None
            authorizer = state_of(self.app).keys  # shared with /api/auth
            live = KeyPolicy.OPTIONAL if config.watchers else KeyPolicy.REQUIRED
            policies = {
                name: live if name in self.robots and self.robots[name].live else KeyPolicy.NONE
                for name in self.graphs
            }
        elif authorizer is None and config.bridge.authorizer_url:
            authorizer = self._own_authorizer = HttpAuthorizer(config.bridge.authorizer_url)
        self.bridge = BridgeServer(self.graphs, config.bridge, authorizer, policies=policies)
        if self.service is not None:
            self.service.metrics.bridge = self.bridge.traffic

    async def start(self) -> None:
        self._loop = asyncio.get_running_loop()
        for name, robot in self.robots.items():
            if robot.live:
                task = asyncio.create_task(
                    LiveRunner(robot, prompt=True).run(), name=f"live {name}"
                )
                task.add_done_callback(_runner_ended)
                self._runners.append(task)
        await _listen(
            self.bridge.start(), self.config.bridge.host, self.config.bridge.port, "--bridge-port"
        )
        filings = Filings(self.config.drives.filings_per_minute)  # shared by the robots
        self.drives = {
            name: Driving(
                station,
                work=self._live_work(),
                file=self._file if self.service is not None else None,
                reserved=self.config.reservations,
                limits=self.config.drives,
                filings=filings,
            )
            for name, station in self.stations.items()
            if station.robot.live
        }
        if self.service is not None:
            self.service.metrics.drives = self.drives
        if self.app is not None:  # the pages link to the robots on the port now known
            state_of(self.app).site = replace(
                self.site, bridge_port=self.bridge.port, drives=self.drives, robots_loop=self._loop
            )
        if self.service is not None and self.http is not None:
            await _listen(
                self.http.start(), self.config.bridge.host, self.config.http_port, "--http-port"
            )
            self.service.serving_at(_reachable(self.http.url()))
            await self.service.start()
            await self.service.start_processes(*self._for_workers(self.http.url()))

    def _for_workers(self, url: str) -> tuple[str, dict[str, str]]:
        """Where the lab's worker processes reach it, and what they add to their
        environment: under TLS, the public address (which its certificate names) when
        there is one, else loopback, trusting the lab's own certificate."""
        service = self.service.config if self.service is not None else None
        if self.config.bridge.tls_cert is None:
            return _reachable(url), {}
        if service is not None and service.public_url:
            return service.public_url, {}
        return _reachable(url), {"SSL_CERT_FILE": str(self.config.bridge.tls_cert)}

    def _live_work(self) -> Path | None:
        """Where live drives are recorded before they are filed (None: no archive)."""
        if self.service is None:
            return None
        folder = (self.service.config.data / "work" / "live").resolve()
        folder.mkdir(parents=True, exist_ok=True)
        return folder

    def _file(self, demo: Demonstration) -> None:
        """File a finished drive from a thread, so the robot goes on stepping meanwhile."""
        assert self.service is not None
        filing = asyncio.get_running_loop().run_in_executor(
            None, self.service.file_demonstration, demo
        )
        self._filings.add(filing)
        filing.add_done_callback(self._filed)

    def _submitted(self) -> None:
        """A trial was queued (the API, on its own thread): wake the workers, on this loop."""
        if self._loop is not None and self.service is not None:
            self._loop.call_soon_threadsafe(self.service.wake)

    def _reservation_changed(self, reservation: Reservation) -> None:
        """A slot was extended or released (the API, from any thread): the clients
        connected with its key get its new end, or are disconnected."""
        loop = self._loop
        if loop is None or self.service is None:
            return
        left = reservation.end - self.service.index.clock()
        reason = f"your slot on {reservation.robot} was released"
        loop.call_soon_threadsafe(self.bridge.reauthorize, ref(reservation.id), left, reason)

    def _filed(self, filing: asyncio.Future[int]) -> None:
        self._filings.discard(filing)
        if not filing.cancelled() and filing.exception() is not None:
            log.error("a demonstration could not be filed", exc_info=filing.exception())

    async def close(self) -> None:
        if self.http is not None:
            await self.http.close()
        for task in self._runners:
            task.cancel()
        for task in self._runners:
            with contextlib.suppress(asyncio.CancelledError):
                await task
        await self.bridge.close()  # clients leave: their drives end and are filed
        for drive in self.drives.values():
            drive.close()
        if self._filings:
            await asyncio.gather(*self._filings, return_exceptions=True)
        if self.service is not None:
            await self.service.close()
        for station in self.stations.values():
            station.close()
        for api in self.rosapi:
            api.close()
        if self._own_authorizer is not None:
            await self._own_authorizer.aclose()
        if self.app is not None:
            state_of(self.app).keys.close()


def _runner_ended(task: asyncio.Task[None]) -> None:
    """A live robot's runner ends only when the lab stops; anything else is a bug, logged."""
    if not task.cancelled() and task.exception() is not None:
        log.error("%s stopped: its robot is frozen", task.get_name(), exc_info=task.exception())


async def _listen(start: Coroutine[Any, Any, None], host: str, port: int, flag: str) -> None:
    """Start a server; a port in use is a ``PortInUse`` naming the flag to change."""
    try:
        await start
    except OSError as err:
        if err.errno == errno.EADDRINUSE:
            raise PortInUse(host, port, flag) from None
        raise


def _tls(bridge: BridgeConfig) -> tuple[Path, Path] | None:
    if bridge.tls_cert is None or bridge.tls_key is None:
        return None
    return bridge.tls_cert, bridge.tls_key


def _reachable(url: str) -> str:
    """``url`` with an address this machine can connect to in place of a wildcard one."""
    return url.replace("://0.0.0.0:", "://127.0.0.1:").replace("://[::]:", "://[::1]:")
