"""A small synchronous rosbridge client for controllers: ``Lab``.

A controller connects, subscribes to the observations it needs, and then, tick by
tick, publishes its commands and calls ``step()``::

    from controllers.client import Lab

    with Lab.connect() as lab:                       # $LAB_BRIDGE_URL
        odom = lab.subscribe("/odom", "nav_msgs/msg/Odometry")
        goal = lab.subscribe("/goal", "geometry_msgs/msg/PointStamped").get()
        while True:
            lab.publish("/cmd_vel", "geometry_msgs/msg/Twist", {"linear": {"x": 0.2}})
            lab.step()                               # EpisodeOver when it ends
            x = odom.latest["pose"]["pose"]["position"]["x"]   # this tick's pose

**The lockstep guarantee.** The lab publishes a tick's observations before it answers
``/lab/step``, the bridge sends frames in the order it produced them, and this client
reads frames in order on the caller's thread (no background dispatch). So when
``step()`` returns, every subscription's ``latest`` holds what the lab published for
that tick, and every callback for it has run. Nothing here sleeps or polls: every
wait is for a frame, with a wall-clock timeout only as a guard against a lab that
stopped answering.

Messages are plain ``dict`` values in the rosbridge JSON form (ROS 2 dialect:
``{"sec", "nanosec"}`` stamps, ``pkg/msg/Type`` names). The client is for one
thread. It uses the standard library only, so it runs in the lab's sandbox as it is.
"""

from __future__ import annotations

import itertools
import json
import logging
import math
import os
import re
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from controllers.connection import Connection, ConnectionClosed, InvalidHandshake, InvalidURI
from controllers.errors import (
    ConnectionLost,
    EpisodeOver,
    LabError,
    LabTimeout,
    ServiceError,
    StatusError,
)

__all__ = [
    "ConnectionLost",
    "EpisodeOver",
    "Lab",
    "LabError",
    "LabTimeout",
    "Message",
    "ServiceError",
    "StatusError",
    "Subscription",
    "Tick",
]

Message = dict[str, Any]
DEFAULT_URL = "ws://127.0.0.1:9090"
STEP = "/lab/step"
EPISODE = "/lab/episode"
EPISODE_TYPE = "lab_msgs/msg/Episode"
MAX_FRAME = 64 * 2**20  # the lab's own limit on a frame
# The lab's /lab/step answers: "tick 12 at 1.200 s: running",
# "tick 600 at 60.000 s: truncated: the time limit of 60 s was reached".
STEP_ANSWER = re.compile(r"tick (\d+) at ([0-9.]+) s: (\w+)(?:: (.*))?", re.DOTALL)
ENDED_ANSWER = re.compile(r".*\((\w+): (.*)\)", re.DOTALL)


@dataclass(frozen=True)
class Tick:
    """Where the episode is after a step: what ``/lab/step`` answered."""

    number: int  # control ticks since the episode began
    time: float  # simulation seconds
    status: str  # running, succeeded, failed or truncated
    reason: str  # why it ended, a sentence (empty while running)
    message: str  # the lab's answer as it was

    @property
    def running(self) -> bool:
        return self.status == "running"

    @property
    def success(self) -> bool:
        """Whether the robot did its task."""
        return self.status == "succeeded"

    @classmethod
    def from_episode(cls, episode: Message, message: str = "") -> Tick:
        """The tick a ``lab_msgs/msg/Episode`` message describes."""
        stamp = episode["header"]["stamp"]
        seconds = stamp["sec"] + stamp["nanosec"] / 1e9
        status, reason = str(episode["status"]), str(episode["reason"])
        text = message or f"tick {episode['tick']} at {seconds:.3f} s: {status}" + (
            f": {reason}" if reason else ""
        )
        return cls(int(episode["tick"]), seconds, status, reason, text)


class Subscription:
    """One topic's messages as they arrive: ``latest``, ``count``, ``get``, ``next``.

    Made by ``Lab.subscribe``. Messages are taken in whenever the client reads from
    the lab (in ``step``, ``call``, ``get``, ``next``), in the order the lab sent them.
    """

    def __init__(
        self,
        lab: Lab,
        topic: str,
        type_name: str,
        callback: Callable[[Message], object] | None,
    ) -> None:
        self.topic = topic
        self.type = type_name
        self.latest: Message | None = None  # the newest message, None before the first
        self.count = 0  # messages received so far
        self._lab = lab
        self._callback = callback

    def _take(self, message: Message) -> None:
        self.latest = message
        self.count += 1
        if self._callback is not None:
            self._callback(message)

    def get(self, timeout: float = 10.0) -> Message:
        """The newest message, waiting for the first one if none has arrived yet.

        For a latched topic (``/goal``, ``/task/goal``) the lab sends its message on
        subscription, so this returns at once after one round trip.
        """
        if self.latest is None:
            self._lab.wait_for(
                lambda: self.latest is not None, timeout, f"a message on {self.topic}"
            )
        assert self.latest is not None
        return self.latest

    def next(self, timeout: float = 10.0) -> Message:
        """Wait for a message newer than the ones received so far and return it.

        A lockstep robot publishes only when stepped, and ``step`` already returns
        with the tick's messages in ``latest``: ``next`` is for what comes on its own
        (a live robot, other clients' topics).
        """
        seen = self.count
        self._lab.wait_for(lambda: self.count > seen, timeout, f"a new message on {self.topic}")
        assert self.latest is not None
        return self.latest

    def unsubscribe(self) -> None:
        """Stop receiving this topic."""
        self._lab._unsubscribe(self)


class Lab:
    """A connection to one robot of the lab (one graph), for one thread.

    Use ``Lab.connect`` to make one, and close it (or use ``with``) when done.
    """

    def __init__(self, socket: Connection, url: str) -> None:
        self.url = url
        self._socket = socket
        self._stepping = False  # in lockstep: commands leave with the next step
        self._ids = itertools.count(1)
        self._subscriptions: dict[str, Subscription] = {}
        self._advertised: dict[str, str] = {}
        self._answers: dict[str, Message] = {}  # service_response frames by id
        self._waiting: set[str] = set()  # ids of calls still expecting an answer
        self._refusals: list[str] = []  # error statuses not yet raised
        self._episode: Subscription | None = None
        self.tick: Tick | None = None  # the newest step's answer
        self.log = logging.getLogger(f"controllers.lab[{url}]")

    # -- connection ------------------------------------------------------------------

    @classmethod
    def connect(
        cls, url: str | None = None, *, key: str | None = None, timeout: float = 10.0
    ) -> Lab:
        """Connect to the robot at ``url`` (default: ``$LAB_BRIDGE_URL``, else
        ``ws://127.0.0.1:9090``). ``key`` is sent first when the lab asks for one.

        Without ``url``, in a sandbox, it connects to the bridge's unix socket
        (``$LAB_BRIDGE_SOCKET``) directly rather than through the relay on port 9090.
        """
        unix = None
        if url is None:
            unix = os.environ.get("LAB_BRIDGE_SOCKET") or None
            if unix is not None and not os.path.exists(unix):
                unix = None
        url = url or os.environ.get("LAB_BRIDGE_URL") or DEFAULT_URL
        try:
            socket = Connection.open(url, unix=unix, timeout=timeout, max_size=MAX_FRAME)
        except (OSError, TimeoutError, InvalidHandshake, InvalidURI) as err:
            # Refused, unreachable, or an HTTP answer instead of a WebSocket (404, 503).
            raise ConnectionLost(url, reason=str(err), opened=False) from err
        lab = cls(socket, url)
        if key is not None:
            lab._send({"op": "auth", "key": key})
        # Errors come back as status frames (warnings are only logged).
        lab._send({"op": "set_level", "level": "warning"})
        return lab

    def close(self) -> None:
        """Close the connection; the lab releases this client's topics and services."""
        self._socket.close()

    def __enter__(self) -> Lab:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- topics ----------------------------------------------------------------------

    def subscribe(
        self,
        topic: str,
        type_name: str,
        callback: Callable[[Message], object] | None = None,
    ) -> Subscription:
        """Receive ``topic`` (of ``type_name``, e.g. ``nav_msgs/msg/Odometry``).

        ``callback``, if given, is called with each message on the caller's thread
        while the client reads (in ``step``, ``call``, ...). Subscribing twice to one
        topic returns the same subscription.
        """
        topic = _absolute(topic)
        if topic in self._subscriptions:
            return self._subscriptions[topic]
        subscription = Subscription(self, topic, type_name, callback)
        self._subscriptions[topic] = subscription
        self._send(
            {"op": "subscribe", "id": self._id("subscribe"), "topic": topic, "type": type_name}
        )
        return subscription

    def _unsubscribe(self, subscription: Subscription) -> None:
        if self._subscriptions.get(subscription.topic) is subscription:
            del self._subscriptions[subscription.topic]
            self._send({"op": "unsubscribe", "topic": subscription.topic})

    def publish(self, topic: str, type_name: str, msg: Mapping[str, Any]) -> None:
        """Publish ``msg`` on ``topic``, advertising it (once) as ``type_name``.

        Publishing does not wait. In lockstep (once ``step`` has been called) the
        message leaves with the next ``step`` (or anything else that reads), in the same
        write; before that, at once. If the lab refuses the message (a NaN, a field the
        type does not have), the next call that reads raises ``StatusError`` with the
        lab's sentence.
        """
        topic = _absolute(topic)
        if self._advertised.get(topic) != type_name:
            self._send(
                {"op": "advertise", "id": self._id("advertise"), "topic": topic, "type": type_name}
            )
            self._advertised[topic] = type_name
        frame = {"op": "publish", "id": self._id("publish"), "topic": topic, "msg": dict(msg)}
        self._send(frame, flush=not self._stepping)

    # -- services --------------------------------------------------------------------

    def call(
        self,
        service: str,
        args: Mapping[str, Any] | Sequence[Any] | None = None,
        timeout: float = 10.0,
    ) -> Message:
        """Call ``service`` and return its response values.

        Raises ``ServiceError`` with the lab's sentence when the call fails (no such
        service, invalid arguments, the provider failed or timed out), and
        ``LabTimeout`` when no answer comes within ``timeout`` seconds.
        """
        answer = self._call(service, args, timeout)
        self._raise_refusals()
        if answer.get("result") is False:
            raise ServiceError(_absolute(service), str(answer.get("values")))
        values = answer.get("values")
        return values if isinstance(values, dict) else {}

    def _call(
        self, service: str, args: Mapping[str, Any] | Sequence[Any] | None, timeout: float
    ) -> Message:
        """Send a call and read until its service_response, which is returned as it is.

        Refusals read meanwhile are kept for the caller to raise.
        """
        service = _absolute(service)
        call_id = self._id("call")
        frame: Message = {
            "op": "call_service",
            "id": call_id,
            "service": service,
            "timeout": timeout,
        }
        if args is not None:
            frame["args"] = dict(args) if isinstance(args, Mapping) else list(args)
        self._waiting.add(call_id)
        self._send(frame)
        try:
            # The lab answers failure itself at ``timeout``; wait a little longer so
            # that its sentence, not ours, is what the caller reads.
            self._read_until(lambda: call_id in self._answers, timeout + 2.0, f"calling {service}")
        finally:
            self._waiting.discard(call_id)
        return self._answers.pop(call_id)

    # -- lockstep --------------------------------------------------------------------

    def step(self, timeout: float = 120.0) -> Tick:
        """Advance the robot one control tick (``/lab/step``) and return where it is.
        (In a match the answer waits for the other side too, which the lab gives a
        minute to take its first step: hence the long ``timeout``.)

        The lab applies every command published before this call, steps, publishes
        the tick's observations and then answers; when this returns, the
        subscriptions hold that tick's observations. Raises ``EpisodeOver`` when the
        answer says the episode ended on this tick (its observations are in the
        subscriptions too) or had already ended.
        """
        self._stepping = True
        answer = self._call(STEP, None, timeout)
        if answer.get("result") is False:
            self._raise_refusals()
            raise ServiceError(STEP, str(answer.get("values")))
        values = answer.get("values")
        values = values if isinstance(values, dict) else {}
        message = str(values.get("message", ""))
        if values.get("success"):
            match = STEP_ANSWER.fullmatch(message)
            if match:
                number, seconds, status, reason = match.groups()
                tick = Tick(int(number), float(seconds), status, reason or "", message)
            else:  # an answer in another form: /lab/episode says where the episode is
                tick = Tick.from_episode(self.episode, message)
        else:
            # "the episode has ended (truncated: the time limit ...)": the tick it ended
            # on is the one /lab/episode still shows.
            ended = ENDED_ANSWER.fullmatch(message)
            if not ended:
                raise ServiceError(STEP, message)
            last = Tick.from_episode(self.episode)
            tick = Tick(last.number, last.time, ended[1], ended[2], message)
        self.tick = tick
        self._raise_refusals()  # a command refused before this step: the step did happen
        if not tick.running:
            raise EpisodeOver(tick)
        return tick

    @property
    def episode(self) -> Message:
        """The newest ``lab_msgs/msg/Episode`` (``/lab/episode``): task, seed, tick,
        status, reason, reward, total_reward, success.

        The first use subscribes to it and waits for its latched message; from then
        on it is that of the newest tick.
        """
        if self._episode is None:
            self._episode = self.subscribe(EPISODE, EPISODE_TYPE)
        return self._episode.get()

    def run(self, policy: Callable[[Tick], object], max_ticks: int | None = None) -> Tick:
        """Call ``policy(tick)`` then ``step()``, over and over, until the episode ends
        (or ``max_ticks`` steps have been taken); return the last tick.

        The first call gets the tick the episode is at (from ``/lab/episode``); each
        later one the tick just stepped, with its observations in the subscriptions.
        """
        tick = self.tick or Tick.from_episode(self.episode)
        for _ in itertools.repeat(None) if max_ticks is None else range(max_ticks):
            policy(tick)
            try:
                tick = self.step()
            except EpisodeOver as over:
                return over.tick
        return tick

    # -- reading ---------------------------------------------------------------------

    def wait_for(self, condition: Callable[[], bool], timeout: float, what: str) -> None:
        """Read frames from the lab, in order, until ``condition()`` holds.

        Raises ``LabTimeout`` naming ``what`` after ``timeout`` wall-clock seconds, and
        ``StatusError`` if the lab refused something meanwhile (once the condition
        holds, or at once if the refusal may be why it never will).
        """
        self._read_until(condition, timeout, what)
        self._raise_refusals()

    def _read_until(self, condition: Callable[[], bool], timeout: float, what: str) -> None:
        deadline = time.monotonic() + timeout
        while not condition():
            # A refusal ends the wait at once unless a call is in flight: then its
            # answer is read first, so that no answer is left behind on the connection.
            if self._refusals and not self._waiting:
                return
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise LabTimeout(what, timeout)
            self._receive(remaining, what, timeout)

    def _raise_refusals(self) -> None:
        if self._refusals:
            refusals, self._refusals = self._refusals, []
            raise StatusError(refusals)

    def _receive(self, remaining: float, what: str, timeout: float) -> None:
        try:
            data = self._socket.recv(timeout=remaining)
        except TimeoutError:
            raise LabTimeout(what, timeout) from None
        except ConnectionClosed as err:
            raise ConnectionLost(self.url, err.code, err.reason) from err
        frame = json.loads(data)
        if not isinstance(frame, dict):
            self.log.warning("ignored a frame that is not a JSON object: %.200s", data)
            return
        op = frame.get("op")
        if op == "publish":
            subscription = self._subscriptions.get(str(frame.get("topic")))
            if subscription is not None:  # else: unsubscribed, still in flight
                subscription._take(frame.get("msg") or {})
        elif op == "service_response":
            call_id = str(frame.get("id"))
            if call_id in self._waiting:
                self._answers[call_id] = frame
            else:
                self.log.warning("dropped an answer to a call no longer waited for: %s", call_id)
        elif op == "status":
            text = str(frame.get("msg", ""))
            if str(frame.get("id")).startswith("call:"):
                pass  # a call's failure is in its service_response, with the same sentence
            elif frame.get("level") == "error":
                self._refusals.append(text)
            else:
                self.log.warning("the lab says: %s", text)
        else:
            self.log.warning("ignored a frame with op %r", op)

    # -- writing ---------------------------------------------------------------------

    def _send(self, frame: Message, *, flush: bool = True) -> None:
        try:
            text = json.dumps(frame, allow_nan=False)
        except ValueError:  # NaN or infinity: sent as null, which the lab refuses by name
            text = json.dumps(_nulls(frame), allow_nan=False)
        try:
            self._socket.send(text)
            if flush:
                self._socket.flush()
        except ConnectionClosed as err:
            raise ConnectionLost(self.url, err.code, err.reason) from err

    def _id(self, op: str) -> str:
        return f"{op}:{next(self._ids)}"


def _nulls(value: Any) -> Any:
    """``value`` with every NaN and infinity replaced by None (JSON null)."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, Mapping):
        return {k: _nulls(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_nulls(v) for v in value]
    return value


def _absolute(name: str) -> str:
    """The graph's name for ``name``: the lab's graphs have one namespace, the root."""
    return name if name.startswith("/") else "/" + name
