"""The robot graph: nodes, topics, services and actions shared by everything in a lab.

A ``Graph`` is one robot's world of names, like a ROS 2 domain: the simulated robot,
the rosapi node, the recorder and every bridge client are ``Node``\\ s in it. Nodes
publish and subscribe to topics, provide and call services, serve and send action
goals. Delivery is synchronous and in-process: ``publish`` returns after every
subscriber's callback has run, so the order of events is the order of calls, which is
what makes lockstep trials reproducible.

**Whose names.** Every node is on one side of the bridge (``Side``): the lab's own
nodes (the robot, rosapi, the recorder) or a client's (one per bridge session). A lab
node that advertises a topic with ``own=True`` makes it the lab's: the robot does so
for everything it publishes (observations, ``/tf``, ``/clock``, ``/lab/episode``, the
cameras), so that what the archive records there is the robot's, never a client's
word. A client node may not advertise (so not publish on) a topic the lab owns, nor
any topic, service or action under the lab's namespaces (``/lab/``, ``/rosapi/``), nor
provide a service or action a lab node provides: each is an ``OwnedError``. The check
is made once, when a publisher or provider is made, so publishing stays a plain
delivery; a claim made after a client advertised revokes the client's publisher.
Taps (the recorder) hear, with each message, the side and the node of its publisher.

Every graph has ``/rosout`` from its creation (``rcl_interfaces/msg/Log``, advertised
by the lab's ``/labd`` node), as every ROS 2 system does; clients may log there too.

A graph is not thread-safe; it lives on one event loop.
"""

from __future__ import annotations

import enum
import itertools
import logging
import time
from collections.abc import Callable, Iterator, Mapping
from typing import Any

from labd.errors import (
    ConflictError,
    GraphError,
    NameError_,
    NotFoundError,
    OwnedError,
    TypeMismatchError,
)
from labd.graph.actions import (
    CANCEL_GOAL,
    CANCEL_SERVICE,
    Action,
    ActionHandler,
    ClientGoal,
    FeedbackCallback,
    GoalResultCallback,
)
from labd.graph.codec import Codec, codec_for
from labd.graph.message import Message
from labd.graph.names import lab_namespace, resolve
from labd.graph.services import Service, ServiceCall, ServiceHandler, ServiceResultCallback
from labd.graph.types import TypeRegistry
from repository.well_known import ROSOUT

Clock = Callable[[], int]  # graph time in nanoseconds
MessageCallback = Callable[[Message], None]
GateCallback = Callable[[Message, "Node | None"], None]  # a gatekeeper told who sent it


class Side(enum.Enum):
    """Which side of the bridge a node is on; a record keeps it for every message."""

    LAB = "lab"  # the lab's own nodes: the robot, rosapi, the log
    CLIENT = "client"  # a bridge client: a trial's controller, a browser, a ROS user


# A message, its publisher's side, and its publisher's node (None: delivered by the graph).
Tap = Callable[["Topic", Message, Side, "Node | None"], None]


def wall_clock() -> int:
    """Graph time for live robots: the wall clock (ROS time, like a real robot)."""
    return time.time_ns()


class Graph:
    """One robot's graph of names."""

    def __init__(
        self, types: TypeRegistry, *, name: str = "lab", clock: Clock = wall_clock
    ) -> None:
        self.types = types
        self.name = name
        self.clock = clock
        self.topics: dict[str, Topic] = {}
        self.services: dict[str, Service] = {}
        self.actions: dict[str, Action] = {}
        self.nodes: dict[str, Node] = {}
        self.params: dict[str, str] = {}
        self.taps: list[Tap] = []
        # Called with each node destroyed (a client that left): a live robot's driver.
        self.node_gone: list[Callable[[Node], None]] = []
        # Called when the graph's shape changes (a publisher, subscription or service
        # comes or goes), many times in one turn of the loop if many do: a Foxglove
        # client's channels follow it.
        self.on_change: list[Callable[[], None]] = []
        # The values the graph's robot runs with (its task's parameters), to read.
        self.parameters: Callable[[], Mapping[str, Any]] = dict
        self.log = logging.getLogger(f"labd.graph.{name}")
        self._node_ids = itertools.count(1)
        # /rosout exists from the start, as on any ROS 2 system (clients check for it).
        self._log_node = self.create_node("/labd")
        self._rosout = self._log_node.advertise(ROSOUT, "rcl_interfaces/msg/Log")

    # -- time and messages ------------------------------------------------------------

    def now(self) -> tuple[int, int]:
        ns = self.clock()
        return ns // 1_000_000_000, ns % 1_000_000_000

    def codec(self, type_name: str) -> Codec:
        return codec_for(self.types, type_name)

    def message(self, type_name: str, value: Mapping[str, Any] | Message) -> Message:
        """Validate ``value`` (JSON-like) as a ``type_name`` message."""
        codec = self.codec(type_name)
        if isinstance(value, Message):
            if value.codec is not codec:
                raise TypeMismatchError("message", "value", value.type_name, codec.type.name)
            return value
        return Message(codec, codec.normalize(value, self.now), self.clock())

    def rosout(self, level: int, logger: str, text: str) -> None:
        """Publish a log line on /rosout (rcl_interfaces/msg/Log), as ROS nodes do."""
        sec, nanosec = self.now()
        self._rosout.publish(
            {"stamp": {"sec": sec, "nanosec": nanosec}, "level": level, "name": logger, "msg": text}
        )

    # -- nodes --------------------------------------------------------------------------

    def create_node(self, name: str, *, side: Side = Side.LAB) -> Node:
        """A new node; a taken name gets a numeric suffix (``/bridge/client_2``).

        Bridge sessions make theirs with ``side=Side.CLIENT``; everything else in the
        lab's process is the lab.
        """
        base = resolve(name)
        unique = base
        while unique in self.nodes:
            unique = f"{base}_{next(self._node_ids)}"
        node = Node(self, unique, side)
        self.nodes[unique] = node
        return node

    # -- topics -------------------------------------------------------------------------

    def topic(self, name: str, type_name: str | None) -> Topic:
        """The topic ``name``, created with ``type_name`` if it does not exist yet."""
        absolute = resolve(name)
        topic = self.topics.get(absolute)
        if topic is None:
            if type_name is None:
                raise NotFoundError("topic", absolute, "no one publishes it yet, so give its type")
            topic = Topic(self, absolute, self.codec(type_name))
            self.topics[absolute] = topic
        elif type_name is not None:
            want = self.codec(type_name).type.name
            if want != topic.type_name:
                raise TypeMismatchError("topic", absolute, topic.type_name, want)
        return topic

    def _forget_topic_if_unused(self, topic: Topic) -> None:
        if not topic.publishers and not topic.subscriptions:
            self.topics.pop(topic.name, None)

    def changed(self) -> None:
        """The graph's shape changed: tell who follows it."""
        for listener in tuple(self.on_change):
            listener()

    # -- introspection (rosapi) -----------------------------------------------------------

    def publishers_of(self, topic: str) -> list[str]:
        t = self.topics.get(topic)
        return sorted({p.node.name for p in t.publishers}) if t else []

    def subscribers_of(self, topic: str) -> list[str]:
        t = self.topics.get(topic)
        return sorted({s.node.name for s in t.subscriptions if not s.hidden}) if t else []

    def iter_nodes(self) -> Iterator[Node]:
        return iter(sorted(self.nodes.values(), key=lambda n: n.name))


class Topic:
    """A named stream of messages of one type."""

    def __init__(self, graph: Graph, name: str, codec: Codec) -> None:
        self.graph = graph
        self.name = name
        self.codec = codec
        self.publishers: list[Publisher] = []
        self.subscriptions: list[Subscription] = []
        self.latched: Message | None = None
        self.owner: Node | None = None  # the lab node that made it the lab's (advertise own=True)
        # Called before a new subscriber joins, so a publisher that skips messages no
        # one hears (a robot's idle topics) can bring the latched one up to date.
        self.refresh: Callable[[], None] | None = None

    @property
    def type_name(self) -> str:
        return self.codec.type.name

    def deliver(
        self, message: Message, latch: bool, side: Side, sender: Node | None = None
    ) -> None:
        """Hand a message to everyone: gatekeepers first, who may still refuse it.

        ``side`` is its publisher's, for the taps; ``sender`` its node, for gates.
        """
        subs = tuple(self.subscriptions)
        for sub in subs:
            if sub.gatekeeper and not sub.closed:
                if sub.gate is not None:
                    sub.gate(message, sender)
                else:
                    sub.callback(message)
        if latch:
            self.latched = message
        for tap in self.graph.taps:
            tap(self, message, side, sender)
        for sub in subs:
            if not sub.gatekeeper and not sub.closed:
                sub.callback(message)


class Publisher:
    """A node's right to publish on a topic."""

    def __init__(self, node: Node, topic: Topic, latch: bool) -> None:
        self.node = node
        self.topic = topic
        self.latch = latch
        self.side = node.side
        self.closed = False
        self.revoked: GraphError | None = None  # why the graph took this publisher back

    def publish(self, value: Mapping[str, Any] | Message, *, latch: bool | None = None) -> Message:
        """Validate and deliver one message; returns it as delivered."""
        self._check_open()
        topic = self.topic
        if isinstance(value, Message):
            message = self.node.graph.message(topic.type_name, value)
        else:
            graph = self.node.graph
            message = Message(topic.codec, topic.codec.normalize(value, graph.now), graph.clock())
        topic.deliver(message, self.latch if latch is None else latch, self.side, self.node)
        return message

    def publish_built(self, data: dict[str, Any]) -> Message:
        """Deliver a value the lab built itself, already in normal form, unvalidated.

        For the robot's observations, which its task builds every tick in normal form
        (exact types, every field, in order): validating them again cost a tenth of a
        tick. ``tests/labd/sim/test_normal_form.py`` holds every task to that form;
        anything a client sends goes through ``publish``.
        """
        self._check_open()
        topic = self.topic
        message = Message(topic.codec, data, self.node.graph.clock())
        topic.deliver(message, self.latch, self.side, self.node)
        return message

    def _check_open(self) -> None:
        if self.closed:
            raise self.revoked or NotFoundError("publisher", self.topic.name, "it was closed")

    def revoke(self, reason: GraphError) -> None:
        """Close this publisher for ``reason``, which every later ``publish`` raises."""
        self.revoked = reason
        self.close()

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        topic = self.topic
        topic.publishers.remove(self)
        self.node.publishers.remove(self)
        if not topic.publishers:
            # As with ROS 2's transient-local durability, the latched message lives
            # with its publishers.
            topic.latched = None
        if topic.owner is self.node and all(p.node is not self.node for p in topic.publishers):
            topic.owner = None  # the lab no longer publishes it
        self.node.graph._forget_topic_if_unused(topic)
        self.node.graph.changed()


class Subscription:
    """A callback on every message of a topic."""

    def __init__(
        self,
        node: Node,
        topic: Topic,
        callback: MessageCallback,
        hidden: bool,
        gatekeeper: bool,
        *,
        gate: GateCallback | None = None,
    ) -> None:
        self.node = node
        self.topic = topic
        self.callback = callback
        self.hidden = hidden  # the recorder and the like do not show up in rosapi
        # A gatekeeper sees each message before anyone else and may refuse it by
        # raising (a robot refusing a NaN command, or a command from a client that is not
        # driving): then no one receives it. A ``gate`` is told who sent it too.
        self.gatekeeper = gatekeeper or gate is not None
        self.gate = gate
        self.closed = False

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        self.topic.subscriptions.remove(self)
        self.node.subscriptions.remove(self)
        self.node.graph._forget_topic_if_unused(self.topic)
        self.node.graph.changed()


class Node:
    """A participant in the graph; destroying it releases all it holds."""

    def __init__(self, graph: Graph, name: str, side: Side = Side.LAB) -> None:
        self.graph = graph
        self.name = name
        self.side = side
        self.publishers: list[Publisher] = []
        self.subscriptions: list[Subscription] = []
        self.services: list[Service] = []
        self.actions: list[Action] = []
        self.calls: list[ServiceCall] = []  # calls this node made that are not answered
        self.goals: list[ClientGoal] = []  # goals this node sent that are not finished
        # Who the client is, when its key said so (the lab's reservations); None: anyone.
        self.user: str | None = None
        # Where a bridge client connects from (limits per address); None: in the lab.
        self.address: str | None = None
        # Which of the bridge's protocols a client speaks, when not rosbridge ("foxglove"):
        # a drive made by commanding is filed under it.
        self.interface = ""
        self.destroyed = False

    def advertise(
        self, topic: str, type_name: str | None, *, latch: bool = False, own: bool = False
    ) -> Publisher:
        """A publisher on ``topic``, which is made with ``type_name`` if it is new.

        ``own``: the topic becomes the lab's (only a lab node may ask): from now on no
        client may advertise it, and the publishers clients already have on it are
        revoked. A client is refused (OwnedError) a topic the lab owns or one under
        the lab's namespaces.
        """
        absolute = resolve(topic)
        if own and self.side is not Side.LAB:
            raise ValueError(f"{self.name} is a client's node: only the lab owns topics")
        if self.side is Side.CLIENT:
            existing = self.graph.topics.get(absolute)
            owner = existing.owner if existing is not None else None
            if owner is not None:
                raise OwnedError("topic", absolute, owner=owner.name)
            _refuse_lab_namespace("topic", absolute)
        t = self.graph.topic(absolute, type_name)
        pub = Publisher(self, t, latch)
        t.publishers.append(pub)
        self.publishers.append(pub)
        if own:  # after joining, so the topic outlives the publishers it revokes
            self._own(t)
        self.graph.changed()
        return pub

    def _own(self, topic: Topic) -> None:
        owner = topic.owner = topic.owner or self
        for pub in tuple(topic.publishers):
            if pub.side is Side.CLIENT:
                pub.revoke(OwnedError("topic", topic.name, owner=owner.name))

    def subscribe(
        self,
        topic: str,
        type_name: str | None,
        callback: MessageCallback,
        *,
        hidden: bool = False,
        latched: bool = True,
        gatekeeper: bool = False,
        gate: GateCallback | None = None,
    ) -> Subscription:
        """Subscribe; the topic's latched message, if any, is delivered at once.

        With ``gate`` the subscription is a gatekeeper told each message's sending node
        (None for a message handed in without one); its ``callback`` still gets the
        latched message.
        """
        t = self.graph.topic(topic, type_name)
        if t.refresh is not None:
            t.refresh()
        sub = Subscription(self, t, callback, hidden, gatekeeper, gate=gate)
        t.subscriptions.append(sub)
        self.subscriptions.append(sub)
        self.graph.changed()
        if latched and t.latched is not None:
            callback(t.latched)
        return sub

    def _claim(self, registry: Mapping[str, Service | Action], kind: str, name: str) -> None:
        """Make ``name`` free for this node: refuse if another node provides it.

        A client may not provide what the lab provides, nor anything under its
        namespaces (OwnedError); two clients, or two lab nodes, conflict.
        """
        existing = registry.get(name)
        if self.side is Side.CLIENT:
            if existing is not None and existing.node.side is Side.LAB:
                raise OwnedError(kind, name, owner=existing.node.name)
            _refuse_lab_namespace(kind, name)
        if existing is not None:
            if existing.node is not self:
                raise ConflictError(kind, name, existing.node.name)
            existing.close()

    def provide_service(self, name: str, type_name: str, handler: ServiceHandler) -> Service:
        absolute = resolve(name)
        stype = self.graph.types.service(type_name)
        self._claim(self.graph.services, "service", absolute)
        service = Service(self, absolute, stype, handler)
        self.graph.services[absolute] = service
        self.services.append(service)
        self.graph.changed()
        return service

    def call_service(
        self,
        name: str,
        request: Mapping[str, Any] | list[Any] | None,
        on_result: ServiceResultCallback,
    ) -> ServiceCall:
        """Call a service; ``on_result`` runs exactly once, maybe before this returns."""
        absolute = resolve(name)
        service = self.graph.services.get(absolute)
        if service is None:
            raise NotFoundError("service", absolute)
        return service.call(self, request, on_result)

    def provide_action(self, name: str, type_name: str, handler: ActionHandler) -> Action:
        """Serve an action, with its ``<action>/_action/cancel_goal`` service (as ROS 2)."""
        absolute = resolve(name)
        atype = self.graph.types.action(type_name)
        cancel_name = absolute + CANCEL_SERVICE
        self._claim(self.graph.actions, "action", absolute)
        self._claim(self.graph.services, "service", cancel_name)
        action = Action(self, absolute, atype, handler)
        self.graph.actions[absolute] = action
        self.actions.append(action)

        def cancel(call: ServiceCall) -> None:
            call.reply(action.cancel_goals(call.request.data))

        action.cancel_service = self.provide_service(cancel_name, CANCEL_GOAL, cancel)
        return action

    def send_goal(
        self,
        name: str,
        goal: Mapping[str, Any] | list[Any] | None,
        on_result: GoalResultCallback,
        on_feedback: FeedbackCallback | None = None,
        *,
        type_name: str | None = None,
    ) -> ClientGoal:
        absolute = resolve(name)
        action = self.graph.actions.get(absolute)
        if action is None:
            raise NotFoundError("action", absolute)
        if type_name is not None:
            want = self.graph.types.action(type_name).name
            if want != action.type.name:
                raise TypeMismatchError("action", absolute, action.type.name, want)
        return action.send_goal(self, goal, on_result, on_feedback)

    def destroy(self) -> None:
        """Release every publisher, subscription, service, action and pending call."""
        if self.destroyed:
            return
        self.destroyed = True
        for call in tuple(self.calls):
            call.abandon()
        for goal in tuple(self.goals):
            goal.abandon()
        for service in tuple(self.services):
            service.close()
        for action in tuple(self.actions):
            action.close()
        for pub in tuple(self.publishers):
            pub.close()
        for sub in tuple(self.subscriptions):
            sub.close()
        self.graph.nodes.pop(self.name, None)
        for listener in tuple(self.graph.node_gone):
            listener(self)

    def __repr__(self) -> str:
        return f"Node({self.name})"


def _refuse_lab_namespace(kind: str, name: str) -> None:
    namespace = lab_namespace(name)
    if namespace is not None:
        raise OwnedError(kind, name, namespace=namespace)


__all__ = [
    "Clock",
    "Graph",
    "NameError_",
    "Node",
    "Publisher",
    "Side",
    "Subscription",
    "Topic",
    "wall_clock",
]
