"""The ``/rosapi`` node: the graph introspection services rosbridge clients expect.

Answered by the lab itself from its graph, under ``/rosapi/NAME`` (and so under the
relative ``rosapi/NAME`` that roslibjs uses). Names under a protected prefix are left
out of every list, so a client cannot even learn that they exist. Parameters are a
flat store of JSON texts per graph, as roslibpy's and roslibjs' ``Param`` expect.

A client that sees the graph under a namespace (a match's side) is answered from its
own view: the bridge maps each service's names on the way in and out, as
``labd.bridge.rosapi_view.VIEWS`` says, and every service here must have its entry.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

import orjson

from labd.bridge.rosapi_view import VIEWS
from labd.errors import GraphError, UnknownTypeError
from labd.graph.graph import Graph, Node
from labd.graph.message import Message
from labd.graph.names import is_protected
from labd.graph.services import ServiceCall
from labd.graph.types import PLACEHOLDER, Field, Kind, MessageType

ROS_VERSION = 2
DISTRO = "jazzy"

Handler = Callable[[dict[str, Any]], Mapping[str, Any] | Message]


class Rosapi:
    """Provides the rosapi services on a graph."""

    def __init__(self, graph: Graph, protected_prefixes: tuple[str, ...]) -> None:
        self.graph = graph
        self.protected = protected_prefixes
        self.node: Node = graph.create_node("/rosapi")
        services: dict[str, tuple[str, Handler]] = {
            "topics": ("Topics", self.topics),
            "topics_for_type": ("TopicsForType", self.topics_for_type),
            "topic_type": ("TopicType", self.topic_type),
            "topics_and_raw_types": ("TopicsAndRawTypes", self.topics_and_raw_types),
            "services": ("Services", self.services),
            "services_for_type": ("ServicesForType", self.services_for_type),
            "service_type": ("ServiceType", self.service_type),
            "service_providers": ("ServiceProviders", self.service_providers),
            "service_node": ("ServiceNode", self.service_node),
            "message_details": ("MessageDetails", self.message_details),
            "service_request_details": ("ServiceRequestDetails", self.request_details),
            "service_response_details": ("ServiceResponseDetails", self.response_details),
            "nodes": ("Nodes", self.nodes),
            "node_details": ("NodeDetails", self.node_details),
            "publishers": ("Publishers", self.publishers),
            "subscribers": ("Subscribers", self.subscribers),
            "action_servers": ("GetActionServers", self.action_servers),
            "get_param": ("GetParam", self.get_param),
            "set_param": ("SetParam", self.set_param),
            "has_param": ("HasParam", self.has_param),
            "delete_param": ("DeleteParam", self.delete_param),
            "get_param_names": ("GetParamNames", self.get_param_names),
            "get_time": ("GetTime", self.get_time),
            "get_ros_version": ("GetROSVersion", self.get_ros_version),
        }
        unmapped = sorted(set(services) ^ set(VIEWS))
        if unmapped:  # a namespaced client would be answered from the whole graph
            raise ValueError(f"rosapi services and their views differ: {unmapped}")
        for name, (type_name, fn) in services.items():
            self.node.provide_service(
                f"/rosapi/{name}", f"rosapi_msgs/srv/{type_name}", _answer(fn)
            )

    def close(self) -> None:
        self.node.destroy()

    def _visible(self, name: str) -> bool:
        return not is_protected(name, self.protected)

    # -- topics -----------------------------------------------------------------------

    def topics(self, _: dict[str, Any]) -> dict[str, Any]:
        names = sorted(n for n in self.graph.topics if self._visible(n))
        return {"topics": names, "types": [self.graph.topics[n].type_name for n in names]}

    def topics_for_type(self, req: dict[str, Any]) -> dict[str, Any]:
        want = self.graph.types.message(req["type"]).name
        return {
            "topics": sorted(
                n for n, t in self.graph.topics.items() if t.type_name == want and self._visible(n)
            )
        }

    def topic_type(self, req: dict[str, Any]) -> dict[str, Any]:
        topic = self.graph.topics.get(_absolute(req["topic"]))
        visible = topic is not None and self._visible(topic.name)
        return {"type": topic.type_name if topic is not None and visible else ""}

    def topics_and_raw_types(self, _: dict[str, Any]) -> dict[str, Any]:
        found = self.topics({})
        texts = [self.graph.types.definition_text(t) for t in found["types"]]
        return {**found, "typedefs_full_text": texts}

    def publishers(self, req: dict[str, Any]) -> dict[str, Any]:
        name = _absolute(req["topic"])
        return {"publishers": self.graph.publishers_of(name) if self._visible(name) else []}

    def subscribers(self, req: dict[str, Any]) -> dict[str, Any]:
        name = _absolute(req["topic"])
        return {"subscribers": self.graph.subscribers_of(name) if self._visible(name) else []}

    # -- services and actions ------------------------------------------------------------

    def services(self, _: dict[str, Any]) -> dict[str, Any]:
        return {"services": sorted(n for n in self.graph.services if self._visible(n))}

    def services_for_type(self, req: dict[str, Any]) -> dict[str, Any]:
        want = self.graph.types.service(req["type"]).name
        return {
            "services": sorted(
                n
                for n, s in self.graph.services.items()
                if s.type.name == want and self._visible(n)
            )
        }

    def service_type(self, req: dict[str, Any]) -> dict[str, Any]:
        service = self.graph.services.get(_absolute(req["service"]))
        ok = service is not None and self._visible(service.name)
        return {"type": service.type.name if service is not None and ok else ""}

    def service_providers(self, req: dict[str, Any]) -> dict[str, Any]:
        node = self.service_node({"service": req["service"]})["node"]
        return {"providers": [node] if node else []}

    def service_node(self, req: dict[str, Any]) -> dict[str, Any]:
        service = self.graph.services.get(_absolute(req["service"]))
        ok = service is not None and self._visible(service.name)
        return {"node": service.node.name if service is not None and ok else ""}

    def action_servers(self, _: dict[str, Any]) -> dict[str, Any]:
        return {"action_servers": sorted(n for n in self.graph.actions if self._visible(n))}

    # -- types ---------------------------------------------------------------------------

    def message_details(self, req: dict[str, Any]) -> dict[str, Any]:
        return {"typedefs": self._typedefs(self.graph.types.message(req["type"]))}

    def request_details(self, req: dict[str, Any]) -> dict[str, Any]:
        return {"typedefs": self._typedefs(self.graph.types.service(req["type"]).request)}

    def response_details(self, req: dict[str, Any]) -> dict[str, Any]:
        return {"typedefs": self._typedefs(self.graph.types.service(req["type"]).response)}

    def _typedefs(self, root: MessageType) -> list[dict[str, Any]]:
        """The type and every message type it contains, each once, root first."""
        out: list[dict[str, Any]] = []
        seen: set[str] = set()
        todo = [root]
        while todo:
            mtype = todo.pop(0)
            if mtype.name in seen:
                continue
            seen.add(mtype.name)
            fields = [f for f in mtype.fields if f.name != PLACEHOLDER]
            out.append(
                {
                    "type": mtype.name,
                    "fieldnames": [f.name for f in fields],
                    "fieldtypes": [_field_type(f) for f in fields],
                    "fieldarraylen": [_array_len(f) for f in fields],
                    "examples": [_example(f) for f in fields],
                    "constnames": [c.name for c in mtype.constants],
                    "constvalues": [str(c.value) for c in mtype.constants],
                }
            )
            todo += [self.graph.types.message(f.message) for f in fields if f.message]
        return out

    # -- nodes -------------------------------------------------------------------------

    def nodes(self, _: dict[str, Any]) -> dict[str, Any]:
        return {"nodes": [n.name for n in self.graph.iter_nodes()]}

    def node_details(self, req: dict[str, Any]) -> dict[str, Any]:
        node = self.graph.nodes.get(_absolute(req["node"]))
        if node is None:
            return {"subscribing": [], "publishing": [], "services": []}
        return {
            "subscribing": sorted(
                {
                    s.topic.name
                    for s in node.subscriptions
                    if not s.hidden and self._visible(s.topic.name)
                }
            ),
            "publishing": sorted(
                {p.topic.name for p in node.publishers if self._visible(p.topic.name)}
            ),
            "services": sorted(s.name for s in node.services if self._visible(s.name)),
        }

    # -- parameters and time ----------------------------------------------------------------

    def get_param(self, req: dict[str, Any]) -> dict[str, Any]:
        value = self.graph.params.get(req["name"])
        if value is None:
            value = req["default_value"] or "null"
        return {"value": value}

    def set_param(self, req: dict[str, Any]) -> dict[str, Any]:
        try:
            orjson.loads(req["value"])
        except orjson.JSONDecodeError:
            raise GraphError(f"the value of {req['name']} must be JSON text") from None
        self.graph.params[req["name"]] = req["value"]
        return {}

    def has_param(self, req: dict[str, Any]) -> dict[str, Any]:
        return {"exists": req["name"] in self.graph.params}

    def delete_param(self, req: dict[str, Any]) -> dict[str, Any]:
        self.graph.params.pop(req["name"], None)
        return {}

    def get_param_names(self, _: dict[str, Any]) -> dict[str, Any]:
        return {"names": sorted(self.graph.params)}

    def get_time(self, _: dict[str, Any]) -> Message:
        sec, nanosec = self.graph.now()
        codec = self.graph.codec("rosapi_msgs/srv/GetTime_Response")
        data = codec.normalize({"time": {"sec": sec, "nanosec": nanosec}}, self.graph.now)
        # roslibpy's Ros.get_time() reads the ROS 1 names, so they travel along in JSON.
        data["time"].update(secs=sec, nsecs=nanosec)
        return Message(codec, data)

    def get_ros_version(self, _: dict[str, Any]) -> dict[str, Any]:
        return {"version": ROS_VERSION, "distro": DISTRO}


def _answer(fn: Handler) -> Callable[[ServiceCall], None]:
    """A service handler whose expected errors become a failed call, not a crash."""

    def handler(call: ServiceCall) -> None:
        try:
            response = fn(call.request.data)
        except (UnknownTypeError, GraphError) as err:
            call.fail(str(err))
            return
        call.reply(response)

    return handler


def _absolute(name: str) -> str:
    return name if name.startswith("/") else "/" + name


def _field_type(field: Field) -> str:
    if field.message:
        return field.message
    return field.base or ""


def _array_len(field: Field) -> int:
    if field.kind is Kind.SCALAR:
        return -1
    return field.length if field.kind is Kind.ARRAY else 0


def _example(field: Field) -> str:
    if field.kind is not Kind.SCALAR:
        return "[]"
    if field.message:
        return "{}"
    return {"string": "", "bool": "False"}.get(field.base or "", "0")
