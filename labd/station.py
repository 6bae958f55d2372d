"""A robot's station: its own graph, the simulated robot on it, and the graph's rosapi.

This is the one place where a robot is assembled, for a live robot of ``labd serve``
(``labd.lab``) as for the private graph of a batch trial (``labd.trial``), so both
look the same to a client: the task's topics under their standard names, ``/lab/*``,
``/rosapi/*`` and ``/rosout``.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from labd.bridge.rosapi import Rosapi
from labd.graph.graph import Graph
from labd.graph.types import TypeRegistry
from labd.sim.registry import TaskSpec
from labd.sim.robot import Robot


class Station:
    """A graph named ``name`` with a robot running ``task`` and a rosapi node."""

    def __init__(
        self,
        types: TypeRegistry,
        name: str,
        task: str | TaskSpec,
        params: Mapping[str, Any] | None = None,
        seed: int = 0,
        *,
        live: bool,
        protected_prefixes: tuple[str, ...],
        node_name: str = "/robot",
        time_limit: float | None = None,
        blind: bool = False,
    ) -> None:
        self.name = name
        self.graph = Graph(types, name=name)
        self.robot = Robot(
            self.graph,
            task,
            params,
            seed,
            live=live,
            node_name=node_name,
            time_limit=time_limit,
            blind=blind,
        )
        self.rosapi = Rosapi(self.graph, protected_prefixes)

    def close(self) -> None:
        self.robot.close()
        self.rosapi.close()
