"""rosapi as a namespaced client sees it: its own side of the graph, spelled its way.

``Rosapi`` answers from the whole graph, and the graph's nodes know nothing of a
session's namespace (it lives in the bridge session alone). So the mapping happens at
the bridge boundary, in the session's ``call_service``: the request's names are mapped
in before the call, the answer's names out after it. ``VIEWS`` says, for every rosapi
service, which request fields and which answer fields are names; ``Rosapi`` refuses to
start with a service that has no entry, and a call on a rosapi service without one is
refused under a namespace, so no service answers a side from the whole graph unseen.

What is a name, and how it is mapped:

- topics, services, actions and nodes (``NAME``, ``NAMES``): ``Namespace.inward`` on
  the way in (``/away/score`` spelled by the home side is ``/home/away/score``, which
  does not exist), ``Namespace.outward`` on the way out; what lies outside the view is
  left out of lists (and of the lists in step with them: a topic's type and type text)
  and is ``""`` where one name is answered. Lists are sorted as the client spells them,
  so their order does not tell a side where its prefix sorts. Node names are mapped as
  any other, so the lab's own nodes (``/labd``, ``/rosapi``, ``/soccer``, the clients'
  ``/bridge/client_N``) are out of a side's view: it lists its own ``/home/...`` nodes
  only, and of its topics' publishers and subscribers only those. An empty name names nothing and is
  passed on as it is (rosapi answers as for a name that does not exist).
- parameters (``PARAM``, ``PARAMS``): the store is free text per graph, and a side's keys
  all live under its prefix, ``gain`` and ``/gain`` alike being ``/home/gain`` (shown as
  ``/gain``). None are shared, not even under ``/lab/``: the lab sets no parameters, and
  a shared key would be a channel from one side to the other.

Type names (``message_details``, ``topics_for_type``'s request) are not the graph's
names and pass as they are.
"""

from __future__ import annotations

import enum
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from labd.errors import GraphError
from labd.graph.graph import Graph
from labd.graph.names import Namespace
from labd.graph.services import args_to_value

ROSAPI = "/rosapi/"


class Kind(enum.Enum):
    NAME = "a topic, service, action or node name"
    NAMES = "a list of such names"
    PARAM = "a parameter's key"
    PARAMS = "a list of parameters' keys"


@dataclass(frozen=True)
class View:
    """Which fields of one rosapi service's request (``ask``) and answer (``tell``) are
    names. ``along``: answer lists in step with the one list of names in ``tell``,
    filtered and ordered with it. Lists of names are answered sorted."""

    ask: Mapping[str, Kind] = field(default_factory=dict)
    tell: Mapping[str, Kind] = field(default_factory=dict)
    along: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        lists = [n for n, kind in self.tell.items() if kind in (Kind.NAMES, Kind.PARAMS)]
        if self.along and len(lists) != 1:
            raise ValueError(f"lists {self.along} go in step with one list of names, not {lists}")


N, NS, P, PS = Kind.NAME, Kind.NAMES, Kind.PARAM, Kind.PARAMS
NOTHING = View()  # no field names anything in the graph

# Every service Rosapi provides, by its name under /rosapi/ (rosapi_msgs/srv/*.srv).
VIEWS: dict[str, View] = {
    "topics": View(tell={"topics": NS}, along=("types",)),
    "topics_for_type": View(tell={"topics": NS}),
    "topic_type": View(ask={"topic": N}),
    "topics_and_raw_types": View(tell={"topics": NS}, along=("types", "typedefs_full_text")),
    "services": View(tell={"services": NS}),
    "services_for_type": View(tell={"services": NS}),
    "service_type": View(ask={"service": N}),
    "service_providers": View(ask={"service": N}, tell={"providers": NS}),
    "service_node": View(ask={"service": N}, tell={"node": N}),
    "message_details": NOTHING,
    "service_request_details": NOTHING,
    "service_response_details": NOTHING,
    "nodes": View(tell={"nodes": NS}),
    "node_details": View(
        ask={"node": N}, tell={"subscribing": NS, "publishing": NS, "services": NS}
    ),
    "publishers": View(ask={"topic": N}, tell={"publishers": NS}),
    "subscribers": View(ask={"topic": N}, tell={"subscribers": NS}),
    "action_servers": View(tell={"action_servers": NS}),
    "get_param": View(ask={"name": P}),
    "set_param": View(ask={"name": P}),
    "has_param": View(ask={"name": P}),
    "delete_param": View(ask={"name": P}),
    "get_param_names": View(tell={"names": PS}),
    "get_time": NOTHING,
    "get_ros_version": NOTHING,
}


@dataclass(frozen=True)
class Viewed:
    """One rosapi call of a namespaced client: its request mapped in, its answer out."""

    view: View
    namespace: Namespace
    graph: Graph
    service: str  # the graph's name, /rosapi/NAME

    def ask(self, args: Mapping[str, Any] | list[Any] | None) -> Any:
        """The request with its names mapped into the graph (NameError_ if malformed).
        Fields that are not strings are left for the service's own check to refuse."""
        values = args_to_value(self.graph.services[self.service].type.request, args)
        if not isinstance(values, dict) or not self.view.ask:
            return values
        out = dict(values)
        for name, kind in self.view.ask.items():
            value = out.get(name, "")
            if not isinstance(value, str):
                continue
            if kind is Kind.PARAM:
                out[name] = param_inward(self.namespace, value)
            elif value:  # "" names nothing, with or without a namespace
                out[name] = self.namespace.inward(value)
        return out

    def tell(self, values: Any) -> Any:
        """The answer with the graph's names as the client spells them, what lies outside
        its view left out."""
        if not isinstance(values, dict) or not self.view.tell:
            return values
        out = dict(values)
        order: list[int] = []  # where each item kept of the one list of names was
        for name, kind in self.view.tell.items():
            value = out[name]
            if kind is Kind.NAME:
                out[name] = (self.namespace.outward(value) or "") if value else ""
                continue
            show = self.namespace.outward if kind is Kind.NAMES else self._param_outward
            # sorted again as shown: sorted as in the graph, shared names would sit
            # before or after the side's own by where its prefix sorts, telling it
            kept = sorted((shown, i) for i, item in enumerate(value) if (shown := show(item)))
            order = [i for _, i in kept]
            out[name] = [shown for shown, _ in kept]
        for name in self.view.along:
            out[name] = [out[name][i] for i in order]
        return out

    def _param_outward(self, key: str) -> str | None:
        return param_outward(self.namespace, key)


def viewed(graph: Graph, service: str, namespace: Namespace | None) -> Viewed | None:
    """How a call on the graph's ``service`` is mapped for a client under ``namespace``;
    None when nothing is (no namespace, not rosapi, or no such service: the call says so).
    GraphError for a rosapi service with no entry in ``VIEWS``: refused, never unmapped."""
    if namespace is None or not service.startswith(ROSAPI) or service not in graph.services:
        return None
    view = VIEWS.get(service[len(ROSAPI) :])
    if view is None:
        raise GraphError(f"{service} is not answered in a namespaced view of the graph")
    return Viewed(view, namespace, graph, service)


def param_inward(namespace: Namespace, key: str) -> str:
    """The store's key for a parameter a client under ``namespace`` names ``key``."""
    return namespace.prefix + (key if key.startswith("/") else "/" + key)


def param_outward(namespace: Namespace, key: str) -> str | None:
    """How a client under ``namespace`` names the store's ``key``; None: not its own."""
    if key.startswith(namespace.prefix + "/"):
        return key[len(namespace.prefix) :]
    return None
