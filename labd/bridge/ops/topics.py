"""advertise, unadvertise, publish, subscribe, unsubscribe.

A client's subscriptions to one topic name (as the client spells it) share one
*stream*: rosbridge clients dispatch incoming messages by topic name, so two
subscriptions to ``/odom`` from one client must not deliver each message twice. The
stream sends at the smallest ``throttle_rate`` of its subscriptions, keeps the
largest ``queue_length`` and the smallest ``fragment_size``; the newest subscription
chooses the compression.

Throttling keeps the newest messages rather than the first: with ``throttle_rate``
and no ``queue_length``, a message that arrives too early waits for the end of the
interval and is replaced by any newer one, so the last state is never lost (rosbridge
drops it). With a ``queue_length`` of N, up to N messages wait and one leaves per
interval.

Whether a client may publish on a topic is the graph's decision, made once when its
publisher is made (``advertise``, or the automatic advertise of a first ``publish``):
the topics a robot publishes are the lab's, and refused with ``OwnedError``. A
publisher the graph takes back later (the lab claimed the topic after the client
advertised it) is forgotten at the next ``publish``, which reports why.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

from labd.bridge.frames import Advertise, Id, Publish, Subscribe, Unadvertise, Unsubscribe
from labd.bridge.outbox import _Entry
from labd.bridge.render import COMPRESSIONS, OutFrame, TopicRenderer
from labd.bridge.session import Capability, Handler, Session
from labd.clock import TimerHandle
from labd.errors import LimitError, MessageError, NotFoundError, OwnedError
from labd.graph.graph import Publisher, Subscription, Topic
from labd.graph.message import Message


@dataclass(frozen=True)
class SubParams:
    throttle_rate: float  # milliseconds
    queue_length: int
    fragment_size: int | None
    compression: str


class Stream:
    """One client's flow of one topic, under the name the client used."""

    def __init__(self, topics: Topics, spelling: str, topic: Topic) -> None:
        self.session = topics.session
        self.spelling = spelling
        self.topic = topic
        self.subs: dict[Id, SubParams] = {}
        self.pending: deque[_Entry] = deque()  # owned by the outbox
        self.dropped = 0
        self.throttle = 0.0  # seconds
        self.limit = 1
        self._held: deque[Message] = deque(maxlen=1)
        self._timer: TimerHandle | None = None
        self._last_sent = float("-inf")
        self._renderer = TopicRenderer(spelling, "none", None)
        self.subscription: Subscription | None = None

    def start(self) -> None:
        """Join the graph; a latched message is delivered at once."""
        self.subscription = self.session.node.subscribe(self.topic.name, None, self.on_message)

    def configure(self) -> None:
        params = list(self.subs.values())
        throttle_ms = min(p.throttle_rate for p in params)
        queue_length = max(p.queue_length for p in params)
        sizes = [p.fragment_size for p in params if p.fragment_size is not None]
        self.throttle = max(0.0, throttle_ms) / 1000.0
        default = self.session.config.default_queue_length
        self.limit = queue_length if queue_length > 0 else default
        self._held = deque(self._held, maxlen=max(queue_length, 1))
        self._renderer = TopicRenderer(
            self.spelling, params[-1].compression, min(sizes) if sizes else None
        )

    def on_message(self, message: Message) -> None:
        if self.throttle <= 0.0:
            self.session.outbox.push_message(self, message, self.limit)
            return
        now = self.session.timers.time()
        if self._timer is None and now - self._last_sent >= self.throttle:
            self._last_sent = now
            self.session.outbox.push_message(self, message, self.limit)
            return
        self._held.append(message)
        if self._timer is None:
            delay = max(0.0, self._last_sent + self.throttle - now)
            self._timer = self.session.timers.call_later(delay, self._release)

    def _release(self) -> None:
        self._timer = None
        if not self._held:
            return
        self._last_sent = self.session.timers.time()
        self.session.outbox.push_message(self, self._held.popleft(), self.limit)
        if self._held:
            self._timer = self.session.timers.call_later(self.throttle, self._release)

    def render(self, message: Message) -> list[OutFrame]:
        return self._renderer.render(message, self.session.fragment_id())

    def close(self) -> None:
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        self._held.clear()
        self.session.outbox.discard(self)
        if self.subscription is not None:
            self.subscription.close()


class Bucket:
    """A token bucket: ``rate`` per second, up to ``burst`` at once."""

    def __init__(self, rate: float, burst: int, clock: Callable[[], float]) -> None:
        self.rate = rate
        self.burst = burst
        self.clock = clock
        self.tokens = float(burst)
        self.at = clock()
        self.dropped = 0  # in a row, since the last message let through

    def take(self) -> bool:
        now = self.clock()
        self.tokens = min(float(self.burst), self.tokens + (now - self.at) * self.rate)
        self.at = now
        if self.tokens < 1.0:
            self.dropped += 1
            return False
        self.tokens -= 1.0
        self.dropped = 0
        return True


class Topics(Capability):
    def __init__(self, session: Session) -> None:
        super().__init__(session)
        self.publishers: dict[str, Publisher] = {}  # by absolute name
        self._by_spelling: dict[str, Publisher] = {}  # fast path for publish
        self.streams: dict[str, Stream] = {}  # by spelling
        self.subscription_count = 0
        self.buckets = {
            topic: Bucket(rate, burst, session.timers.time)
            for topic, rate, burst in session.config.rate_limits
        }

    def handlers(self) -> Iterable[Handler[Any]]:
        return (
            Handler(Advertise, self.advertise),
            Handler(Unadvertise, self.unadvertise),
            Handler(Publish, self.publish),
            Handler(Subscribe, self.subscribe),
            Handler(Unsubscribe, self.unsubscribe),
        )

    # -- publishing -------------------------------------------------------------------

    def advertise(self, op: Advertise) -> None:
        name = self.session.resolve(op.topic)
        pub = self.publishers.get(name)
        if pub is not None and pub.closed:  # revoked by the graph: ask it again
            self._forget(pub)
            pub = None
        if pub is not None:
            self.session.graph.topic(name, op.type)  # same type, or TypeMismatchError
            pub.latch = op.latch
            return
        if len(self.publishers) >= self.session.config.max_publishers:
            raise LimitError("advertised topics", self.session.config.max_publishers)
        self.publishers[name] = self.session.node.advertise(name, op.type, latch=op.latch)
        self.session.report("info", f"advertised {name}", op.id)

    def unadvertise(self, op: Unadvertise) -> None:
        name = self.session.resolve(op.topic)
        pub = self.publishers.get(name)
        if pub is None:
            self.session.report("warning", f"unadvertise: {op.topic} is not advertised", op.id)
            return
        self._forget(pub)
        pub.close()

    def _forget(self, pub: Publisher) -> None:
        if self.publishers.get(pub.topic.name) is pub:
            del self.publishers[pub.topic.name]
        self._by_spelling = {k: v for k, v in self._by_spelling.items() if v is not pub}

    def publish(self, op: Publish) -> None:
        pub = self._by_spelling.get(op.topic)
        if pub is None:
            pub = self._publisher_for(op)
        bucket = self.buckets.get(pub.topic.name) if self.buckets else None
        if bucket is not None and not bucket.take():
            if bucket.dropped == 1:  # say it once per burst of drops, not per message
                self.session.report(
                    "warning",
                    f"publish: {pub.topic.name} takes at most {bucket.rate:g} messages a"
                    " second from a client; the rest are dropped",
                    op.id,
                )
            return
        try:
            hold = self.session.hold
            if hold is None:
                pub.publish(op.msg, latch=op.latch)
            else:  # checked now, delivered now or once the barrier lets it through
                message = self.session.graph.message(pub.topic.type_name, op.msg)
                if not hold(self.session, pub, message, op.id):
                    pub.publish(message, latch=op.latch)
        except MessageError as err:
            raise err.prefixed("msg") from None
        except OwnedError:
            self._forget(pub)  # revoked: the next publish asks the graph again
            raise

    def _publisher_for(self, op: Publish) -> Publisher:
        name = self.session.resolve(op.topic)
        pub = self.publishers.get(name)
        if pub is None or pub.closed:
            # Auto-advertise with the type the topic already has.
            if name not in self.session.graph.topics:
                raise NotFoundError("topic", name, "advertise it with its type before publishing")
            self.advertise(
                Advertise(topic=op.topic, type=self.session.graph.topics[name].type_name)
            )
            pub = self.publishers[name]
        if len(self._by_spelling) < 4 * self.session.config.max_publishers:
            self._by_spelling[op.topic] = pub
        return pub

    # -- subscribing ------------------------------------------------------------------

    def subscribe(self, op: Subscribe) -> None:
        config = self.session.config
        name = self.session.resolve(op.topic)
        topic = self.session.graph.topic(name, op.type)
        compression = op.compression or "none"
        if compression not in COMPRESSIONS:
            self.session.report(
                "warning",
                f"subscribe: compression {compression!r} is not one of "
                f"{', '.join(COMPRESSIONS)}; sending without",
                op.id,
            )
            compression = "none"
        if op.throttle_rate < 0 or op.queue_length < 0:
            raise MessageError(
                "must not be negative",
                ["throttle_rate" if op.throttle_rate < 0 else "queue_length"],
            )
        stream = self.streams.get(op.topic)
        fresh = stream is None
        if stream is None:
            stream = Stream(self, op.topic, topic)
        if op.id not in stream.subs:
            if self.subscription_count >= config.max_subscriptions:
                raise LimitError("subscriptions", config.max_subscriptions)
            self.subscription_count += 1
        stream.subs[op.id] = SubParams(
            float(op.throttle_rate), op.queue_length, op.fragment_size, compression
        )
        stream.configure()
        if fresh:
            self.streams[op.topic] = stream
            stream.start()
        self.session.report("info", f"subscribed to {name}", op.id)

    def unsubscribe(self, op: Unsubscribe) -> None:
        name = self.session.resolve(op.topic)
        candidates = (
            [self.streams[op.topic]]
            if op.topic in self.streams
            else [s for s in self.streams.values() if s.topic.name == name]
        )
        removed = 0
        for stream in candidates:
            ids = (
                [op.id]
                if op.id is not None and op.id in stream.subs
                else (list(stream.subs) if op.id is None else [])
            )
            for sub_id in ids:
                del stream.subs[sub_id]
                removed += 1
            if not stream.subs:
                del self.streams[stream.spelling]
                stream.close()
            elif ids:
                stream.configure()
        self.subscription_count -= removed
        if not removed:
            what = f"subscription {op.id!r} to {op.topic}" if op.id is not None else op.topic
            self.session.report("warning", f"unsubscribe: not subscribed ({what})", op.id)

    def close(self) -> None:
        for stream in self.streams.values():
            stream.close()
        self.streams.clear()
        for pub in self.publishers.values():
            pub.close()
        self.publishers.clear()
        self._by_spelling.clear()
