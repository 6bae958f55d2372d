"""The lab as one object: its graphs, their rosapi nodes, and the bridge serving them.

``labd serve`` builds one; tests build one on port 0. Robots, the recorder and the
HTTP API join here as they land.
"""

from __future__ import annotations

import logging

from labd.bridge.auth import Authorizer, HttpAuthorizer
from labd.bridge.rosapi import Rosapi
from labd.bridge.server import BridgeServer
from labd.config import LabConfig
from labd.graph.graph import Graph
from labd.graph.types import TypeRegistry

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
        self.graphs: dict[str, Graph] = {"playground": Graph(self.types, name="playground")}
        self.rosapi = [Rosapi(g, config.bridge.protected_prefixes) for g in self.graphs.values()]
        self._own_authorizer: HttpAuthorizer | None = None
        if authorizer is None and config.bridge.authorizer_url:
            authorizer = self._own_authorizer = HttpAuthorizer(config.bridge.authorizer_url)
        self.bridge = BridgeServer(self.graphs, config.bridge, authorizer)

    async def start(self) -> None:
        await self.bridge.start()

    async def close(self) -> None:
        await self.bridge.close()
        for api in self.rosapi:
            api.close()
        if self._own_authorizer is not None:
            await self._own_authorizer.aclose()
