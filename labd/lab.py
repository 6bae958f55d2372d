"""The lab as one object: its graphs, their rosapi nodes, and the bridge serving them.

``labd serve`` builds one; tests build one on port 0. With a service configured it
also runs the archive, the queue's workers and the HTTP API over them.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging

from labd.api.app import create_app
from labd.api.server import HttpServer
from labd.bridge.auth import Authorizer, HttpAuthorizer
from labd.bridge.rosapi import Rosapi
from labd.bridge.server import BridgeServer
from labd.config import LabConfig
from labd.graph.graph import Graph
from labd.graph.types import TypeRegistry
from labd.service import Service
from labd.sim.robot import LiveRunner, Robot

log = logging.getLogger("labd.lab")


class Lab:
    """Owns everything ``labd serve`` runs; ``start`` and ``close`` it on one event loop."""

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
        self.robots: dict[str, Robot] = {}
        for robot in config.robots:
            graph = self.graphs[robot.name] = Graph(self.types, name=robot.name)
            node = "/" + robot.name.replace("-", "_")
            self.robots[robot.name] = Robot(
                graph, robot.task, dict(robot.params), robot.seed, live=robot.live, node_name=node
            )
        if config.playground:
            self.graphs["playground"] = Graph(self.types, name="playground")
        self.rosapi = [Rosapi(g, config.bridge.protected_prefixes) for g in self.graphs.values()]
        self._runners: list[asyncio.Task[None]] = []
        self._own_authorizer: HttpAuthorizer | None = None
        if authorizer is None and config.bridge.authorizer_url:
            authorizer = self._own_authorizer = HttpAuthorizer(config.bridge.authorizer_url)
        self.bridge = BridgeServer(self.graphs, config.bridge, authorizer)
        self.service: Service | None = None
        self.http: HttpServer | None = None
        if config.service is not None:
            self.service = Service(config.service, self.types)
            self.http = HttpServer(create_app(self.service), config.bridge.host, config.http_port)

    async def start(self) -> None:
        for name, robot in self.robots.items():
            if robot.live:
                task = asyncio.create_task(LiveRunner(robot).run(), name=f"live {name}")
                self._runners.append(task)
        await self.bridge.start()
        if self.service is not None and self.http is not None:
            await self.http.start()
            await self.service.start()

    async def close(self) -> None:
        if self.http is not None:
            await self.http.close()
        if self.service is not None:
            await self.service.close()
        for task in self._runners:
            task.cancel()
        for task in self._runners:
            with contextlib.suppress(asyncio.CancelledError):
                await task
        await self.bridge.close()
        for robot in self.robots.values():
            robot.close()
        for api in self.rosapi:
            api.close()
        if self._own_authorizer is not None:
            await self._own_authorizer.aclose()
