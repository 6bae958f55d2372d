"""One client's bridge session: the protocol core, without I/O.

A ``Session`` takes the frames a client sends (``receive``) and produces the frames
to send back (``next_frames``), talking to the robot graph in between. It does no
I/O: the server around it moves bytes, and the session asks it for the three things
it cannot do itself through a ``Transport``: wake the writer, close the connection,
and check a key with the authorizer. Time comes from ``Timers``. Tests drive it with
strings.

Every op goes through one dispatcher, which applies the rules that hold for all ops:
authorization first, protected names never cross, errors become a status frame (to a
client that asked for status with ``set_level``), a log line, and a line on
``/rosout``. It dispatches once: each capability (``labd.bridge.ops``) declares a
``Handler`` per op it takes, and the session keeps one table from op type to handler,
made when the client connects.
"""

from __future__ import annotations

import enum
import itertools
import logging
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any, Generic, Protocol, TypeVar

from labd.bridge import frames
from labd.bridge.frames import Auth, CallService, Id, Op
from labd.bridge.outbox import Outbox
from labd.bridge.render import OutFrame, finish, json_frame
from labd.clock import TimerHandle, Timers
from labd.config import BridgeConfig
from labd.errors import FrameError, LabError, NameError_
from labd.graph.codec import dumps
from labd.graph.graph import Graph, Publisher, Side
from labd.graph.message import Message
from labd.graph.names import Namespace, is_protected, resolve

LEVELS = {"none": 0, "error": 1, "warning": 2, "info": 3}
ROSOUT_LEVELS = {"error": 40, "warning": 30, "info": 20}
POLICY_VIOLATION = 1008


class Transport(Protocol):
    """What the session needs from the connection it runs on."""

    def wake(self) -> None:
        """Frames are waiting in ``next_frames``."""

    def close(self, code: int, reason: str) -> None:
        """Close the connection with this WebSocket close code and reason."""

    def authorize(self, key: str) -> None:
        """Check ``key``; answer later with ``Session.grant`` or ``Session.refuse``."""


class Hold(Protocol):
    """Who may keep a client's message from the graph for a while: a match's step
    barrier takes a team's commands when they arrive and delivers them when both teams
    have stepped (``labd.match``). True: taken, delivered later (a refusal then is told
    to the session); False: delivered now."""

    def __call__(
        self, session: Session, publisher: Publisher, message: Message, op_id: Id
    ) -> bool: ...


class AuthState(enum.Enum):
    OPEN = "open"  # no authorization needed, or granted
    AWAITING = "awaiting"  # the first frame must be an auth frame
    AUTHORIZING = "authorizing"  # the authorizer is being asked
    CLOSED = "closed"


OpT = TypeVar("OpT", bound=Op)
CapT = TypeVar("CapT", bound="Capability")


@dataclass(frozen=True)
class Handler(Generic[OpT]):
    """One op a capability takes, and the method that handles it."""

    op: type[OpT]
    handle: Callable[[OpT], None]


class Capability:
    """A family of ops: declares their handlers, and releases what it holds when the
    client leaves."""

    def __init__(self, session: Session) -> None:
        self.session = session

    def handlers(self) -> Iterable[Handler[Any]]:
        """The ops this capability takes, each with its handler."""
        raise NotImplementedError

    def close(self) -> None:
        """The client has left: release everything."""


class Session:
    """The protocol state of one connected client."""

    text_as_str = False  # rosbridge takes text and binary frames alike, as bytes

    def __init__(
        self,
        graph: Graph,
        config: BridgeConfig,
        timers: Timers,
        transport: Transport,
        *,
        client_id: int,
        capabilities: list[Callable[[Session], Capability]],
        auth_required: bool = False,
        auth_optional: bool = False,
        url_key: str | None = None,
        namespace: Namespace | None = None,
        hold: Hold | None = None,
    ) -> None:
        """``namespace``: the client's view of the graph (a match's side: its names are
        mapped under it, ``names.Namespace``); None: the graph's own names. ``hold``:
        what may keep its messages back until later (a match's step barrier)."""
        self.graph = graph
        self.config = config
        self.timers = timers
        self.transport = transport
        self.client_id = client_id
        self.log = logging.LoggerAdapter(
            logging.getLogger("labd.bridge.session"), {"client": client_id}
        )
        self.node = graph.create_node(f"/bridge/client_{client_id}", side=Side.CLIENT)
        self.namespace = namespace
        self.hold = hold
        self.outbox = Outbox(config.max_queue_bytes, transport.wake)
        self.status_level: int | None = None  # None until the client sends set_level
        self.closed = False
        self._fragment_ids = itertools.count(1)
        self._tokens = float(config.log_burst)
        self._tokens_at = timers.time()
        self._suppressed = 0
        self._capabilities = tuple(make(self) for make in capabilities)
        self._handlers: dict[type[Op], Callable[[Any], None]] = {}
        for cap in self._capabilities:
            for handler in cap.handlers():
                if handler.op in self._handlers:
                    raise ValueError(f"two capabilities handle {handler.op.__name__}")
                self._handlers[handler.op] = handler.handle
        self._held: list[str | bytes] = []  # frames received while authorizing
        self._auth_timer: TimerHandle | None = None
        self._expiry: TimerHandle | None = None
        self._warning: TimerHandle | None = None
        self.auth = AuthState.OPEN
        # With a key optional, an open session may still present one (once).
        self.accepts_key = auth_optional and not auth_required
        self.grant_ref: str | None = None  # what the granted key opens (Grant.ref)
        self.expires_at: float | None = None
        if auth_required:
            self.auth = AuthState.AWAITING
            self._auth_timer = timers.call_later(config.auth_timeout, self._auth_timed_out)
            if url_key is not None:
                self._start_authorizing(url_key)
        elif self.accepts_key and url_key is not None:
            self._start_authorizing(url_key)

    # -- input --------------------------------------------------------------------------

    def receive(self, data: str | bytes) -> None:
        """Handle one frame from the client."""
        if self.closed:
            return
        if self.auth is not AuthState.OPEN:
            self._receive_unauthorized(data)
            return
        if len(data) > self.config.max_message_size:
            self.report(
                "error",
                f"a frame of {len(data)} bytes is over the limit of "
                f"{self.config.max_message_size}; it was dropped",
            )
            return
        op = self.op_of(data)
        if op is None:
            return
        if isinstance(op, Auth):
            self._late_auth(op)
            return
        self.dispatch(op)

    def op_of(self, data: str | bytes) -> Op | None:
        """The op a frame holds; None when there is none to dispatch (the frame was
        refused, and the client told why)."""
        try:
            return frames.parse(data)
        except FrameError as err:
            self.report("error", str(err), frames.peek_id(data))
            return None

    def capability(self, kind: type[CapT]) -> CapT:
        """This session's capability of the class ``kind``."""
        for cap in self._capabilities:
            if isinstance(cap, kind):
                return cap
        raise LookupError(f"the session has no {kind.__name__} capability")

    def dispatch(self, op: Op) -> None:
        handle = self._handlers.get(type(op))
        name = op.__struct_config__.tag
        op_id: Id = getattr(op, "id", None)
        if handle is None:
            self.report("warning", f"{name} is not available here", op_id)
            return
        protected = self._protected_name(op)
        if protected is not None:
            self._refuse_protected(op, protected, op_id)
            return
        try:
            handle(op)
        except LabError as err:
            self.report("error", f"{name}: {err}", op_id)
        except Exception:
            # A bug in the lab, not in the client's frame: keep the traceback, tell the
            # client something went wrong on our side, and keep the connection.
            self.log.exception("internal error handling %s", name)
            self.report("error", f"{name}: internal error in the lab (logged)", op_id)

    def resolve(self, name: object) -> str:
        """The graph's absolute name for ``name`` as this client spells it: under its
        namespace, if it has one (NameError_ if malformed)."""
        return resolve(name) if self.namespace is None else self.namespace.inward(name)

    def _protected_name(self, op: Op) -> str | None:
        prefixes = self.config.protected_prefixes
        if not prefixes:
            return None
        name = (
            getattr(op, "topic", None)
            or getattr(op, "service", None)
            or getattr(op, "action", None)
        )
        if not isinstance(name, str):
            return None
        try:
            absolute = self.resolve(name)  # the graph's name, under a namespace
        except NameError_:
            return None  # malformed; the handler says so
        return name if is_protected(absolute, prefixes) else None

    def _refuse_protected(self, op: Op, name: str, op_id: Id) -> None:
        if isinstance(op, CallService):
            # The rosjs rule: a call on a protected service answers an empty object.
            reply: dict[str, Any] = {
                "op": "service_response",
                "service": name,
                "values": {},
                "result": True,
            }
            if op_id is not None:
                reply["id"] = op_id
            self.send(reply)
        self.report("error", f"{op.__struct_config__.tag}: {name} is protected", op_id)

    # -- output ------------------------------------------------------------------------

    def next_frames(self) -> list[OutFrame] | None:
        """The next frames to send, in order, or None when nothing waits."""
        return self.outbox.pop()

    def send(
        self, frame: dict[str, Any], compression: str = "none", fragment_size: int | None = None
    ) -> None:
        """Queue a control frame (a reply or status); never dropped."""
        if self.closed:
            return
        if compression == "none" and fragment_size is None:
            self.outbox.push_frame(json_frame(frame))
        else:
            for part in finish(dumps(frame), compression, fragment_size, self.fragment_id()):
                self.outbox.push_frame(part)
        if self.outbox.overflowed:
            self.close_connection(POLICY_VIOLATION, "the client does not read its replies")

    def fragment_id(self) -> str:
        return f"fragment:{self.client_id}:{next(self._fragment_ids)}"

    def report(self, level: str, text: str, op_id: Id = None) -> None:
        """Send a status if the client asked for this level; log warnings and errors.

        Warnings and errors also go out on /rosout. Logging is rate-limited per client,
        so a client that floods bad frames cannot flood the log.
        """
        if self.status_level is not None and LEVELS[level] <= self.status_level:
            status: dict[str, Any] = {"op": "status", "level": level, "msg": self.told(text)}
            if op_id is not None:
                status["id"] = op_id
            self.send(status)
        if level == "info":
            self.log.debug("client %d: %s", self.client_id, text)
            return
        if not self._take_log_token():
            return
        log_level = logging.WARNING if level == "error" else logging.INFO
        self.log.log(log_level, "client %d: %s", self.client_id, text)
        self.graph.rosout(ROSOUT_LEVELS[level], self.node.name.lstrip("/").replace("/", "."), text)

    def told(self, text: str) -> str:
        """``text`` as this client may read it: the graph's names under its namespace
        spelled as it spells them (a match's side is not told which it is). Every
        status and failed answer goes out through here, graph errors included."""
        if self.namespace is None:
            return text
        return text.replace(self.namespace.prefix + "/", "/")

    def _take_log_token(self) -> bool:
        now = self.timers.time()
        self._tokens = min(
            float(self.config.log_burst),
            self._tokens + (now - self._tokens_at) * self.config.log_rate,
        )
        self._tokens_at = now
        if self._tokens < 1.0:
            self._suppressed += 1
            return False
        self._tokens -= 1.0
        if self._suppressed:
            count, self._suppressed = self._suppressed, 0
            self.log.warning("client %d: %d more log lines suppressed", self.client_id, count)
        return True

    # -- authorization -------------------------------------------------------------------

    def _receive_unauthorized(self, data: str | bytes) -> None:
        if self.auth is AuthState.AUTHORIZING:
            self._held.append(data)
            if len(self._held) > 1000:
                self.close_connection(POLICY_VIOLATION, "too many frames before authorization")
            return
        if self.auth is not AuthState.AWAITING:
            return
        try:
            op = frames.parse(data)
        except FrameError:
            op = None
        key = (op.key or op.mac) if isinstance(op, Auth) else None
        if not key:
            self.close_connection(
                POLICY_VIOLATION, 'the first frame must be {"op": "auth", "key": ...}'
            )
            return
        self._start_authorizing(key)

    def _late_auth(self, op: Auth) -> None:
        """An auth frame on an open session: where a key is optional, the client
        presents one now (frames after it wait for the answer); else it is out of place."""
        key = op.key or op.mac
        if not self.accepts_key:
            self.report("warning", "auth: this connection needs no key, or has one already")
            return
        if not key:
            self.report("error", 'auth: give the key, {"op": "auth", "key": ...}')
            return
        self._start_authorizing(key)

    def _start_authorizing(self, key: str) -> None:
        self.auth = AuthState.AUTHORIZING
        self.accepts_key = False
        self.transport.authorize(key)

    def grant(self, seconds: float, *, user: str | None = None, ref: str | None = None) -> None:
        """The authorizer accepted the key for ``seconds``; it belongs to ``user`` (when
        the authorizer says) and opens ``ref``."""
        if self.auth is not AuthState.AUTHORIZING:
            return
        if seconds <= 0:
            self.refuse("the key has no time left")
            return
        self.auth = AuthState.OPEN
        if self._auth_timer is not None:
            self._auth_timer.cancel()
            self._auth_timer = None
        self.node.user = user
        self.grant_ref = ref
        self._schedule_expiry(seconds)
        self.log.info(
            "client %d authorized for %.0f s%s",
            self.client_id,
            seconds,
            f" as {user}" if user else "",
        )
        held, self._held = self._held, []
        for data in held:
            self.receive(data)

    def reauthorize(self, seconds: float, reason: str) -> None:
        """The key's time changed (its slot was extended or released): it now ends in
        ``seconds``, or, if none are left, the connection closes saying ``reason``."""
        if self.closed or self.expires_at is None:
            return
        if seconds <= 0:
            self._cancel_expiry()
            self.close_connection(POLICY_VIOLATION, reason)
            return
        self._schedule_expiry(seconds)
        self.log.info("client %d: its key now ends in %.0f s", self.client_id, seconds)

    def _schedule_expiry(self, seconds: float) -> None:
        self._cancel_expiry()
        self.expires_at = self.timers.time() + seconds
        self._expiry = self.timers.call_later(seconds, self._expired)
        ahead = self.config.expiry_warning
        if 0 < ahead < seconds:
            self._warning = self.timers.call_later(seconds - ahead, self._warn)

    def _cancel_expiry(self) -> None:
        for timer in (self._expiry, self._warning):
            if timer is not None:
                timer.cancel()
        self._expiry = self._warning = None

    def _warn(self) -> None:
        self._warning = None
        if self.expires_at is None:
            return
        left = max(0.0, self.expires_at - self.timers.time())
        self.report(
            "warning",
            f"the time of your key ends in {left:.0f} s: this connection will close then"
            " (a reservation may be extended if the next slot is free)",
        )

    def refuse(self, reason: str) -> None:
        if self.auth is AuthState.CLOSED or self.closed:
            return
        self.close_connection(POLICY_VIOLATION, f"authorization refused: {reason}")

    def _auth_timed_out(self) -> None:
        self._auth_timer = None
        if self.auth is not AuthState.OPEN:
            self.close_connection(POLICY_VIOLATION, "no authorization in time")

    def _expired(self) -> None:
        self._expiry = None
        self.expires_at = None
        self.close_connection(POLICY_VIOLATION, "the authorization has expired")

    # -- lifecycle ---------------------------------------------------------------------

    def close_connection(self, code: int, reason: str) -> None:
        """Ask the transport to close; the session is released when it has."""
        if self.auth is not AuthState.OPEN:
            self.auth = AuthState.CLOSED
        self.log.info("client %d: closing (%d %s)", self.client_id, code, reason)
        self.transport.close(code, reason)

    def close(self) -> None:
        """The connection is gone: release every subscription, publisher, service, goal."""
        if self.closed:
            return
        self.closed = True
        self.auth = AuthState.CLOSED
        for timer in (self._auth_timer, self._expiry, self._warning):
            if timer is not None:
                timer.cancel()
        for cap in self._capabilities:
            cap.close()
        self.node.destroy()
        self._held.clear()
