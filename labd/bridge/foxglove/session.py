"""A client that speaks Foxglove's WebSocket protocol: a bridge session like any other.

``FoxgloveSession`` is a ``Session`` (``labd.bridge.session``) with Foxglove's frames
in and out: the same key rules and expiry, the same bounded outbox, the same graph
node, so what holds for a rosbridge client holds here. A subscription is a graph
subscription (a camera starts for it as for any), a client's message goes through
the robot's driving rule (one driver, others watch; ``labd.live``), and a service
call reaches the same providers.

What the protocol adds, by capability:

- ``Channels``: every topic that has a publisher is a channel, advertised with its
  ROS 2 definition (``ros2msg``) and served in CDR, the bytes the recorder writes
  (``Message.cdr``, made once per message whoever asks). Channels follow the graph:
  a topic that appears is advertised, one that goes is unadvertised. Before a
  message of a new instant the client is sent the graph's time (the ``time``
  capability: a robot's graph runs on simulation time); a new episode sends it back.
  A channel with bytes in it (a camera) keeps its two newest messages for a slow
  client, others the configured queue length; the outbox drops the oldest beyond.
- ``ClientPublish``: a client advertises channels of its own, in CDR or JSON, and
  sends messages on them (Foxglove's Teleop panel on ``/cmd_vel``).
- ``Calls``: every service is advertised; a call in CDR or JSON is answered in the
  encoding it came in, or with ``serviceCallFailure`` saying why.
- ``Parameters``: the robot's task parameters (``camera_width``) and those set
  through rosapi, to read; setting one is refused.
- ``ConnectionGraph``: who publishes, subscribes and provides what, and its changes.

Protected names never cross: their topics are no channels, their services are not
advertised. Problems reach the client as ``status`` frames (Foxglove shows them),
warnings and errors alike; a connection closed by the lab says why in a status first.
"""

from __future__ import annotations

import itertools
import struct
from collections import deque
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

import orjson
from rosbags.serde import SerdeError

from labd.bridge.foxglove import wire
from labd.bridge.foxglove.wire import (
    ClientData,
    GetParameters,
    ServiceRequest,
    SetParameters,
    SubscribeConnectionGraph,
    SubscribeParameterUpdates,
    UnsubscribeConnectionGraph,
    UnsubscribeParameterUpdates,
)
from labd.bridge.frames import Id, Op
from labd.bridge.ops.topics import Bucket
from labd.bridge.outbox import _Entry
from labd.bridge.render import OutFrame
from labd.bridge.rosapi import DISTRO
from labd.bridge.session import (
    POLICY_VIOLATION,
    AuthState,
    Capability,
    Handler,
    Hold,
    Session,
    Transport,
)
from labd.clock import TimerHandle, Timers
from labd.config import BridgeConfig
from labd.errors import FrameError, GraphError, LabError, LimitError, MessageError
from labd.graph.codec import Codec
from labd.graph.graph import Graph, Publisher, Subscription
from labd.graph.message import Message
from labd.graph.names import is_protected, resolve
from labd.graph.services import ServiceResult
from labd.graph.types import full_name

ENCODINGS = ("cdr", "json")  # what the lab takes from a client, CDR first (as ROS bridges)
CAPABILITIES = ("clientPublish", "services", "parameters", "time", "connectionGraph")
BYTES_KEPT = 2  # messages a channel with bytes in it (a camera) keeps for a slow client
STATUS_LEVELS = {"info": 0, "warning": 1, "error": 2}
MESSAGE_HEAD = 13  # opcode, subscription id, time: what a message adds to its CDR


@dataclass(frozen=True)
class ServerInfo:
    """What a bridge tells every Foxglove client of a graph when it connects."""

    name: str  # shown by the app
    session_id: str  # changes when the bridge restarts: the app then starts afresh


class FoxgloveSession(Session):
    """The protocol state of one Foxglove client."""

    text_as_str = True  # Foxglove tells text from binary frames

    def __init__(
        self,
        graph: Graph,
        config: BridgeConfig,
        timers: Timers,
        transport: Transport,
        *,
        client_id: int,
        info: ServerInfo,
        auth_required: bool = False,
        auth_optional: bool = False,
        url_key: str | None = None,
        hold: Hold | None = None,
    ) -> None:
        self.time_sent = -1  # the graph time last sent (a Time frame), ns
        self._opened = False
        self._follow: TimerHandle | None = None
        super().__init__(
            graph,
            config,
            timers,
            transport,
            client_id=client_id,
            capabilities=[Channels, ClientPublish, Calls, Parameters, ConnectionGraph],
            auth_required=auth_required,
            auth_optional=auth_optional,
            url_key=url_key,
            hold=hold,
        )
        self.node.interface = "foxglove"
        self.send(
            {
                "op": "serverInfo",
                "name": info.name,
                "capabilities": list(CAPABILITIES),
                "supportedEncodings": list(ENCODINGS),
                "metadata": {"ROS_DISTRO": DISTRO, "robot": graph.name},
                "sessionId": info.session_id,
            }
        )
        if self.auth is AuthState.OPEN:
            self._open()

    def _open(self) -> None:
        """Authorized: advertise the graph, and follow it."""
        self._opened = True
        self.graph.on_change.append(self._graph_changed)
        self.follow_graph()

    def grant(self, seconds: float, *, user: str | None = None, ref: str | None = None) -> None:
        super().grant(seconds, user=user, ref=ref)
        if self.auth is AuthState.OPEN and not self._opened and not self.closed:
            self._open()

    def _graph_changed(self) -> None:
        if self._follow is None and not self.closed:
            self._follow = self.timers.call_later(0, self.follow_graph)

    def follow_graph(self) -> None:
        """Tell the client what changed in the graph since it was last told."""
        self._follow = None
        if self.closed:
            return
        self.capability(Channels).follow()
        self.capability(Calls).follow()
        self.capability(ConnectionGraph).follow()

    def visible(self, name: str) -> bool:
        return not is_protected(name, self.config.protected_prefixes)

    # -- input --------------------------------------------------------------------------

    def op_of(self, data: str | bytes) -> Op | None:
        """A text frame's op; a binary frame (a message, a service call) is handled
        here whole, and has none to dispatch."""
        try:
            if isinstance(data, bytes):
                self._receive_binary(wire.parse_binary(data))
                return None
            return wire.parse_text(data)
        except FrameError as err:
            self.report("error", str(err))
            return None

    def _receive_binary(self, frame: ClientData | ServiceRequest) -> None:
        try:
            if isinstance(frame, ClientData):
                self.capability(ClientPublish).publish(frame)
            else:
                self.capability(Calls).call(frame)
        except LabError as err:
            self.report("error", str(err))
        except Exception:
            self.log.exception("internal error handling a binary frame")
            self.report("error", "internal error in the lab (logged)")

    # -- output ------------------------------------------------------------------------

    def send_binary(self, frame: OutFrame) -> None:
        """Queue a binary control frame (a service's answer); never dropped."""
        if self.closed:
            return
        self.outbox.push_frame(frame)
        if self.outbox.overflowed:
            self.close_connection(POLICY_VIOLATION, "the client does not read its replies")

    def report(self, level: str, text: str, op_id: Id = None, *, status_id: str = "") -> None:
        """Warnings and errors reach the client as statuses (``status_id``: a status the
        app replaces rather than adds to), and the log as for any client."""
        if level != "info" and not self.closed:
            status: dict[str, Any] = {
                "op": "status",
                "level": STATUS_LEVELS[level],
                "message": text,
            }
            if status_id:
                status["id"] = status_id
            self.send(status)
        super().report(level, text, op_id)

    def time_frames(self, stamp_ns: int) -> list[OutFrame]:
        """The Time frame to send before a message of ``stamp_ns``, if it is of a new
        instant; the graph's clock behind what was sent means a new episode, whose
        time starts again."""
        if self.graph.clock() < self.time_sent:
            self.time_sent = -1
        if stamp_ns <= self.time_sent:
            return []
        self.time_sent = stamp_ns
        return [wire.time_frame(stamp_ns)]

    # -- lifecycle ---------------------------------------------------------------------

    def close_connection(self, code: int, reason: str) -> None:
        if not self.closed and not self.outbox.overflowed:  # the app shows statuses
            self.send({"op": "status", "level": STATUS_LEVELS["error"], "message": reason})
        super().close_connection(code, reason)

    def close(self) -> None:
        if self._follow is not None:
            self._follow.cancel()
            self._follow = None
        if self._graph_changed in self.graph.on_change:
            self.graph.on_change.remove(self._graph_changed)
        super().close()


def _session(capability: Capability) -> FoxgloveSession:
    session = capability.session
    assert isinstance(session, FoxgloveSession)
    return session


# -- channels ------------------------------------------------------------------------------


@dataclass(frozen=True)
class Channel:
    id: int
    topic: str
    type_name: str


class Feed:
    """One subscription of the client: a channel's messages, as MessageData frames."""

    def __init__(self, session: FoxgloveSession, sub_id: int, channel: Channel) -> None:
        self.session = session
        self.id = sub_id
        self.channel = channel
        self.pending: deque[_Entry] = deque()  # owned by the outbox
        self.dropped = 0
        codec = session.graph.codec(channel.type_name)
        self.limit = BYTES_KEPT if codec.has_binary else session.config.default_queue_length
        self.subscription: Subscription | None = None

    def start(self) -> None:
        """Join the graph; a latched message is delivered at once."""
        self.subscription = self.session.node.subscribe(
            self.channel.topic, self.channel.type_name, self.on_message
        )

    def on_message(self, message: Message) -> None:
        size = len(message.cdr()) + MESSAGE_HEAD
        self.session.outbox.push_message(self, message, self.limit, size)

    def render(self, message: Message) -> list[OutFrame]:
        frames = self.session.time_frames(message.stamp_ns)
        frames.append(wire.message_data(self.id, message.stamp_ns, message.cdr()))
        return frames

    def close(self) -> None:
        self.session.outbox.discard(self)
        if self.subscription is not None:
            self.subscription.close()
            self.subscription = None


class Channels(Capability):
    """The graph's topics as channels, and the client's subscriptions to them."""

    def __init__(self, session: Session) -> None:
        super().__init__(session)
        self.channels: dict[int, Channel] = {}
        self.by_topic: dict[str, Channel] = {}
        self.feeds: dict[int, Feed] = {}  # by subscription id
        self._ids = itertools.count(1)
        self._schemas: dict[str, str] = {}  # definition text by type

    def handlers(self) -> Iterable[Handler[Any]]:
        return (
            Handler(wire.Subscribe, self.subscribe),
            Handler(wire.Unsubscribe, self.unsubscribe),
        )

    def follow(self) -> None:
        """Advertise the topics that appeared, unadvertise those that went."""
        session = _session(self)
        now = {
            name: topic.type_name
            for name, topic in session.graph.topics.items()
            if topic.publishers and session.visible(name)
        }
        gone = [
            channel for name, channel in self.by_topic.items() if now.get(name) != channel.type_name
        ]
        for channel in gone:
            del self.by_topic[channel.topic]
            del self.channels[channel.id]
            for feed in [f for f in self.feeds.values() if f.channel is channel]:
                del self.feeds[feed.id]
                feed.close()
        if gone:
            session.send({"op": "unadvertise", "channelIds": [c.id for c in gone]})
        new = []
        for name in sorted(now.keys() - self.by_topic.keys()):
            channel = Channel(next(self._ids), name, now[name])
            self.channels[channel.id] = self.by_topic[name] = channel
            new.append(self._advertised(channel))
        if new:
            session.send({"op": "advertise", "channels": new})

    def _advertised(self, channel: Channel) -> dict[str, Any]:
        schema = self._schemas.get(channel.type_name)
        if schema is None:
            schema = self.session.graph.types.definition_text(channel.type_name)
            self._schemas[channel.type_name] = schema
        return {
            "id": channel.id,
            "topic": channel.topic,
            "encoding": "cdr",
            "schemaName": channel.type_name,
            "schema": schema,
            "schemaEncoding": "ros2msg",
        }

    def subscribe(self, op: wire.Subscribe) -> None:
        session = _session(self)
        limit = session.config.max_subscriptions
        for request in op.subscriptions:
            channel = self.channels.get(request.channelId)
            if request.id in self.feeds:
                session.report("warning", f"subscribe: subscription id {request.id} is in use")
            elif channel is None:
                session.report("warning", f"subscribe: no channel with id {request.channelId}")
            elif any(feed.channel is channel for feed in self.feeds.values()):
                session.report("warning", f"subscribe: {channel.topic} is subscribed already")
            elif len(self.feeds) >= limit:
                session.report("error", f"subscribe: {LimitError('subscriptions', limit)}")
            else:
                feed = self.feeds[request.id] = Feed(session, request.id, channel)
                feed.start()

    def unsubscribe(self, op: wire.Unsubscribe) -> None:
        for sub_id in op.subscriptionIds:
            feed = self.feeds.pop(sub_id, None)
            if feed is None:
                self.session.report("warning", f"unsubscribe: no subscription with id {sub_id}")
            else:
                feed.close()

    def close(self) -> None:
        for feed in self.feeds.values():
            feed.close()
        self.feeds.clear()


# -- client publishing ---------------------------------------------------------------------


@dataclass
class ClientChannel:
    id: int
    topic: str
    encoding: str
    publisher: Publisher


class ClientPublish(Capability):
    """Channels the client advertises, and the messages it sends on them."""

    def __init__(self, session: Session) -> None:
        super().__init__(session)
        self.channels: dict[int, ClientChannel] = {}
        self.buckets = {
            topic: Bucket(rate, burst, session.timers.time)
            for topic, rate, burst in session.config.rate_limits
        }

    def handlers(self) -> Iterable[Handler[Any]]:
        return (
            Handler(wire.Advertise, self.advertise),
            Handler(wire.Unadvertise, self.unadvertise),
        )

    def advertise(self, op: wire.Advertise) -> None:
        session = _session(self)
        for given in op.channels:
            try:
                self._advertise(given)
            except LabError as err:
                session.report("error", f"advertise: {given.topic}: {err}")

    def _advertise(self, given: wire.ClientChannel) -> None:
        session = _session(self)
        if given.encoding not in ENCODINGS:
            raise MessageError(f"encoding {given.encoding!r} is not one of {', '.join(ENCODINGS)}")
        type_name = full_name(given.schemaName, "msg")
        if type_name is None:
            raise MessageError(f"{given.schemaName!r} is not a message type's name")
        name = resolve(given.topic)
        if not session.visible(name):
            raise GraphError(f"{name} is protected")
        old = self.channels.pop(given.id, None)
        if old is not None:
            old.publisher.close()
        if len(self.channels) >= session.config.max_publishers:
            raise LimitError("advertised channels", session.config.max_publishers)
        publisher = session.node.advertise(name, type_name)
        self.channels[given.id] = ClientChannel(given.id, name, given.encoding, publisher)

    def unadvertise(self, op: wire.Unadvertise) -> None:
        for channel_id in op.channelIds:
            channel = self.channels.pop(channel_id, None)
            if channel is None:
                self.session.report("warning", f"unadvertise: no channel with id {channel_id}")
            else:
                channel.publisher.close()

    def publish(self, data: ClientData) -> None:
        session = _session(self)
        channel = self.channels.get(data.channel)
        if channel is None:
            raise MessageError(f"a message on channel {data.channel}, which was not advertised")
        publisher = channel.publisher
        bucket = self.buckets.get(channel.topic) if self.buckets else None
        if bucket is not None and not bucket.take():
            if bucket.dropped == 1:
                session.report(
                    "warning",
                    f"{channel.topic} takes at most {bucket.rate:g} messages a second from a"
                    " client; the rest are dropped",
                )
            return
        try:
            value = decode(publisher.topic.codec, channel.encoding, data.payload)
        except MessageError as err:
            raise MessageError(f"{channel.topic}: {err}") from None
        try:
            hold = session.hold
            if hold is None:
                publisher.publish(value)
            else:
                message = session.graph.message(publisher.topic.type_name, value)
                if not hold(session, publisher, message, None):
                    publisher.publish(message)
        except MessageError as err:
            raise err.prefixed(channel.topic) from None
        except LabError as err:  # not driving, not reserved: one status, replaced each time
            session.report("warning", f"{channel.topic}: {err}", status_id=channel.topic)

    def close(self) -> None:
        for channel in self.channels.values():
            channel.publisher.close()
        self.channels.clear()


def decode(codec: Codec, encoding: str, payload: bytes) -> dict[str, Any]:
    """A client's message or request, in ``encoding``, as a value to validate."""
    if encoding == "json":
        try:
            value = orjson.loads(payload) if payload.strip() else {}
        except orjson.JSONDecodeError as err:
            raise MessageError(f"the JSON does not parse ({err.msg})") from None
        if not isinstance(value, dict):
            raise MessageError(f"a {codec.type.name} must be a JSON object")
        return value
    if encoding != "cdr":
        raise MessageError(f"encoding {encoding!r} is not one of {', '.join(ENCODINGS)}")
    try:
        obj = codec.type_store.deserialize_cdr(payload, codec.type.name)
    except (SerdeError, ValueError, IndexError, KeyError, struct.error, UnicodeDecodeError) as err:
        raise MessageError(f"the bytes are not a CDR {codec.type.name} ({err})") from None
    decoded: dict[str, Any] = codec.from_rosbags(obj)
    return decoded


# -- services ------------------------------------------------------------------------------


class Calls(Capability):
    """The graph's services, advertised, and the client's calls of them."""

    def __init__(self, session: Session) -> None:
        super().__init__(session)
        self.ids: dict[str, int] = {}  # service name -> id
        self.names: dict[int, str] = {}
        self.waiting = 0
        self._ids = itertools.count(1)
        self._timers: set[TimerHandle] = set()

    def handlers(self) -> Iterable[Handler[Any]]:
        return ()

    def follow(self) -> None:
        session = _session(self)
        graph = session.graph
        now = {name for name in graph.services if session.visible(name)}
        gone = [name for name in self.ids if name not in now]
        if gone:
            ids = [self.ids.pop(name) for name in gone]
            for service_id in ids:
                del self.names[service_id]
            session.send({"op": "unadvertiseServices", "serviceIds": ids})
        new = []
        for name in sorted(now - self.ids.keys()):
            service_id = next(self._ids)
            self.ids[name] = service_id
            self.names[service_id] = name
            new.append(self._advertised(service_id, name))
        if new:
            session.send({"op": "advertiseServices", "services": new})

    def _advertised(self, service_id: int, name: str) -> dict[str, Any]:
        graph = self.session.graph
        stype = graph.services[name].type
        request = graph.types.definition_text(stype.request.name)
        response = graph.types.definition_text(stype.response.name)
        return {
            "id": service_id,
            "name": name,
            "type": stype.name,
            "request": _schema(stype.request.name, request),
            "response": _schema(stype.response.name, response),
            "requestSchema": request,  # for clients older than the two above
            "responseSchema": response,
        }

    def call(self, request: ServiceRequest) -> None:
        session = _session(self)
        config = session.config

        def fail(text: str) -> None:
            session.send(
                {
                    "op": "serviceCallFailure",
                    "serviceId": request.service,
                    "callId": request.call,
                    "message": text,
                }
            )

        name = self.names.get(request.service)
        service = session.graph.services.get(name) if name is not None else None
        if name is None or service is None:
            fail(f"no service with id {request.service}")
            return
        if self.waiting >= config.max_pending:
            fail(str(LimitError("calls waiting for an answer", config.max_pending)))
            return
        try:
            args = decode(service.request_codec, request.encoding, request.payload)
        except MessageError as err:
            fail(f"{name}: {err}")
            return
        timer: TimerHandle | None = None

        def on_result(result: ServiceResult) -> None:
            self.waiting -= 1
            if timer is not None:
                timer.cancel()
                self._timers.discard(timer)
            if not result.ok or result.response is None:
                fail(result.error or f"{name} failed")
                return
            response = result.response
            payload = response.cdr() if request.encoding == "cdr" else response.json()
            session.send_binary(
                wire.service_call_response(request.service, request.call, request.encoding, payload)
            )

        self.waiting += 1
        try:
            pending = session.node.call_service(name, args, on_result)
        except LabError as err:
            self.waiting -= 1
            fail(str(err))
            return
        if pending.done or config.service_timeout <= 0:
            return

        def expire() -> None:
            if timer is not None:
                self._timers.discard(timer)
            if not pending.done:
                pending.abandon()
                on_result(
                    ServiceResult(
                        False, None, f"{name} did not answer within {config.service_timeout:g} s"
                    )
                )

        timer = session.timers.call_later(config.service_timeout, expire)
        self._timers.add(timer)

    def close(self) -> None:
        for timer in self._timers:
            timer.cancel()
        self._timers.clear()


def _schema(type_name: str, text: str) -> dict[str, str]:
    return {"encoding": "cdr", "schemaName": type_name, "schemaEncoding": "ros2msg", "schema": text}


# -- parameters ----------------------------------------------------------------------------


class Parameters(Capability):
    """The robot's parameters, to read."""

    def handlers(self) -> Iterable[Handler[Any]]:
        return (
            Handler(GetParameters, self.get),
            Handler(SetParameters, self.set),
            Handler(SubscribeParameterUpdates, self.not_offered),
            Handler(UnsubscribeParameterUpdates, self.not_offered),
        )

    def values(self) -> dict[str, Any]:
        graph = self.session.graph
        values: dict[str, Any] = dict(graph.parameters())
        for name, text in graph.params.items():  # set through rosapi, as JSON
            try:
                values[name] = orjson.loads(text)
            except orjson.JSONDecodeError:
                values[name] = text
        return values

    def get(self, op: GetParameters) -> None:
        values = self.values()
        names = op.parameterNames or sorted(values)
        self._send([n for n in names if n in values], values, op.id)

    def set(self, op: SetParameters) -> None:
        values = self.values()
        names = [p.name for p in op.parameters]
        self.session.report("error", "setParameters: the robot's parameters are read-only")
        self._send([n for n in names if n in values], values, op.id)  # the app's undone

    def not_offered(self, op: SubscribeParameterUpdates | UnsubscribeParameterUpdates) -> None:
        self.session.report(
            "warning",
            f"{op.__struct_config__.tag}: the robot's parameters do not change while it runs",
        )

    def _send(self, names: list[str], values: Mapping[str, Any], op_id: str | None) -> None:
        frame: dict[str, Any] = {
            "op": "parameterValues",
            "parameters": [_parameter(name, values[name]) for name in names],
        }
        if op_id is not None:
            frame["id"] = op_id
        self.session.send(frame)


def _parameter(name: str, value: Any) -> dict[str, Any]:
    parameter = {"name": name, "value": value}
    if isinstance(value, float):
        parameter["type"] = "float64"
    elif isinstance(value, list) and value and all(isinstance(v, float) for v in value):
        parameter["type"] = "float64_array"
    return parameter


# -- the connection graph ------------------------------------------------------------------

Edges = dict[str, frozenset[str]]  # a topic or service -> node names


class ConnectionGraph(Capability):
    """Who publishes, subscribes and provides what, for a client that asks."""

    def __init__(self, session: Session) -> None:
        super().__init__(session)
        self.following = False
        self._told: tuple[Edges, Edges, Edges] = ({}, {}, {})

    def handlers(self) -> Iterable[Handler[Any]]:
        return (
            Handler(SubscribeConnectionGraph, self.subscribe),
            Handler(UnsubscribeConnectionGraph, self.unsubscribe),
        )

    def subscribe(self, op: SubscribeConnectionGraph) -> None:
        self.following = True
        self._told = ({}, {}, {})
        self.follow()

    def unsubscribe(self, op: UnsubscribeConnectionGraph) -> None:
        self.following = False

    def state(self) -> tuple[Edges, Edges, Edges]:
        session = _session(self)
        graph = session.graph
        published: Edges = {}
        subscribed: Edges = {}
        for name, topic in graph.topics.items():
            if not session.visible(name):
                continue
            if topic.publishers:
                published[name] = frozenset(p.node.name for p in topic.publishers)
            readers = frozenset(s.node.name for s in topic.subscriptions if not s.hidden)
            if readers:
                subscribed[name] = readers
        services: Edges = {
            name: frozenset({service.node.name})
            for name, service in graph.services.items()
            if session.visible(name)
        }
        return published, subscribed, services

    def follow(self) -> None:
        if not self.following:
            return
        now = self.state()
        before = self._told
        if now == before:
            return
        self._told = now
        keys = ("publishedTopics", "subscribedTopics", "advertisedServices")
        ids = ("publisherIds", "subscriberIds", "providerIds")
        removed_topics = (before[0].keys() | before[1].keys()) - (now[0].keys() | now[1].keys())
        removed_services = before[2].keys() - now[2].keys()
        frame: dict[str, Any] = {"op": "connectionGraphUpdate"}
        for key, id_key, new, old in zip(keys, ids, now, before, strict=True):
            gone = removed_services if key == "advertisedServices" else removed_topics
            frame[key] = [
                {"name": name, id_key: sorted(new.get(name, ()))}
                for name in sorted((new.keys() | old.keys()) - gone)
                if old.get(name) != new.get(name)
            ]
        frame["removedTopics"] = sorted(removed_topics)
        frame["removedServices"] = sorted(removed_services)
        self.session.send(frame)
