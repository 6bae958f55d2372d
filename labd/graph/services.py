"""Services in the graph: one provider per name, calls answered exactly once.

A provider is a ``ServiceHandler``: it receives a ``ServiceCall`` and answers it, now
or later, with ``reply`` or ``fail``. The caller's callback runs exactly once with a
``ServiceResult``. A call whose caller has gone (timed out, disconnected) is
*abandoned*: its late answer is dropped, and the provider may be told through
``on_abandon``.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from labd.errors import MessageError
from labd.graph.codec import codec_for
from labd.graph.message import Message
from labd.graph.types import PLACEHOLDER, MessageType, ServiceType

if TYPE_CHECKING:
    from labd.graph.graph import Node


@dataclass(frozen=True)
class ServiceResult:
    """The answer to a call: a response, or a reason it failed."""

    ok: bool
    response: Message | None = None
    error: str = ""


ServiceResultCallback = Callable[[ServiceResult], None]
ServiceHandler = Callable[["ServiceCall"], None]

_call_ids = itertools.count(1)


def args_to_value(mtype: MessageType, args: Mapping[str, Any] | list[Any] | None) -> Any:
    """Request arguments as a dict; a list fills the fields in order (rosbridge allows it)."""
    if args is None:
        return {}
    if isinstance(args, list):
        names = [f.name for f in mtype.fields if f.name != PLACEHOLDER]
        if len(args) > len(names):
            raise MessageError(f"has {len(args)} items but {mtype.name} has {len(names)} fields")
        return dict(zip(names, args, strict=False))
    return args


class Service:
    """A named service and the node that provides it."""

    def __init__(self, node: Node, name: str, stype: ServiceType, handler: ServiceHandler) -> None:
        self.node = node
        self.name = name
        self.type = stype
        self.handler = handler
        self.pending: dict[int, ServiceCall] = {}
        self.closed = False
        registry = node.graph.types
        self.request_codec = codec_for(registry, stype.request.name)
        self.response_codec = codec_for(registry, stype.response.name)

    def call(
        self,
        caller: Node,
        args: Mapping[str, Any] | list[Any] | None,
        on_result: ServiceResultCallback,
    ) -> ServiceCall:
        """Validate the request and hand it to the provider (MessageError if invalid)."""
        graph = self.node.graph
        value = args_to_value(self.type.request, args)
        request = Message(self.request_codec, self.request_codec.normalize(value, graph.now))
        call = ServiceCall(self, caller, request, on_result)
        self.pending[call.id] = call
        caller.calls.append(call)
        self.handler(call)
        return call

    def close(self) -> None:
        """Withdraw the service; calls in progress fail."""
        if self.closed:
            return
        self.closed = True
        for call in tuple(self.pending.values()):
            call.fail(f"the provider of {self.name} went away")
        graph = self.node.graph
        if graph.services.get(self.name) is self:
            del graph.services[self.name]
        self.node.services.remove(self)
        graph.changed()


class ServiceCall:
    """One call in progress."""

    def __init__(
        self, service: Service, caller: Node, request: Message, on_result: ServiceResultCallback
    ) -> None:
        self.id = next(_call_ids)
        self.service = service
        self.caller = caller
        self.request = request
        self._on_result: ServiceResultCallback | None = on_result
        self.on_abandon: Callable[[], None] | None = None

    @property
    def done(self) -> bool:
        return self._on_result is None

    def reply(self, value: Mapping[str, Any] | Message) -> None:
        """Answer with a response; MessageError (to the provider) if it does not fit.

        An invalid response also fails the call, so the caller is not left waiting.
        """
        if self.done:
            return
        codec = self.service.response_codec
        if isinstance(value, Message):
            response = value
        else:
            try:
                response = Message(codec, codec.normalize(value, self.service.node.graph.now))
            except MessageError as err:
                self.fail(
                    f"the provider of {self.service.name} sent an invalid response: "
                    f"{err.prefixed('values')}"
                )
                raise
        self._finish(ServiceResult(True, response))

    def fail(self, reason: str) -> None:
        self._finish(ServiceResult(False, None, reason))

    def abandon(self) -> None:
        """The caller no longer waits (timeout or gone); a later answer is dropped."""
        if self.done:
            return
        self._on_result = None
        self._forget()
        if self.on_abandon is not None:
            self.on_abandon()

    def _finish(self, result: ServiceResult) -> None:
        callback = self._on_result
        if callback is None:
            return
        self._on_result = None
        self._forget()
        callback(result)

    def _forget(self) -> None:
        self.service.pending.pop(self.id, None)
        if self in self.caller.calls:
            self.caller.calls.remove(self)


def simple_handler(
    fn: Callable[[dict[str, Any]], Mapping[str, Any]],
) -> ServiceHandler:
    """Wrap a function from request values to response values as a service handler."""

    def handler(call: ServiceCall) -> None:
        call.reply(fn(call.request.data))

    return handler
