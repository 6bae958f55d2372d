"""call_service, service_response, advertise_service, unadvertise_service.

A client calls any service in the graph: the lab's own (``/rosapi/*``, ``/lab/step``)
or one that another client provides. The answer is a ``service_response`` with
``result: true`` and the response ``values``, or ``result: false`` with a sentence in
``values`` saying why (no such service, invalid arguments, timed out, the provider
failed or left). A client under a namespace asks rosapi in its own names and is
answered from its own view of the graph (``labd.bridge.rosapi_view``). A call without
a ``timeout`` gives up after the configured default (5 s); a timeout of zero or less
waits for ever.

A client that advertises a service receives each call as a ``call_service`` frame
with a fresh ``id`` and answers it with a ``service_response`` carrying that id.
"""

from __future__ import annotations

import itertools
from collections.abc import Iterable
from typing import Any

from labd.bridge.frames import (
    AdvertiseService,
    CallService,
    ServiceResponse,
    UnadvertiseService,
)
from labd.bridge.rosapi_view import Viewed, viewed
from labd.bridge.session import Capability, Handler, Session
from labd.clock import TimerHandle
from labd.errors import GraphError, LimitError, MessageError
from labd.graph.codec import dumps
from labd.graph.services import Service, ServiceCall, ServiceResult


def failure_text(values: Any, default: str) -> str:
    """A provider's failure ``values`` as one sentence."""
    if isinstance(values, str) and values:
        return values
    if values in (None, {}, [], ""):
        return default
    return dumps(values).decode()


class Services(Capability):
    def __init__(self, session: Session) -> None:
        super().__init__(session)
        self.provided: dict[str, Service] = {}  # by absolute name
        self.incoming: dict[str, ServiceCall] = {}  # calls to this client's services, by id
        self.waiting = 0  # calls this client made that are not answered yet
        self._timers: dict[int, TimerHandle] = {}  # timeouts of those calls
        self._ids = itertools.count(1)

    def handlers(self) -> Iterable[Handler[Any]]:
        return (
            Handler(CallService, self.call),
            Handler(ServiceResponse, self.respond),
            Handler(AdvertiseService, self.advertise),
            Handler(UnadvertiseService, self.unadvertise),
        )

    # -- calling ---------------------------------------------------------------------------

    def call(self, op: CallService) -> None:
        session = self.session
        config = session.config

        def answer(ok: bool, values: Any) -> None:
            frame: dict[str, Any] = {
                "op": "service_response",
                "service": op.service,
                "values": values if ok else session.told(str(values)),  # why, as it spells it
                "result": ok,
            }
            if op.id is not None:
                frame["id"] = op.id
            session.send(frame, op.compression or "none", op.fragment_size)

        if self.waiting >= config.max_pending:
            answer(False, str(LimitError("calls waiting for an answer", config.max_pending)))
            return
        call_id = next(self._ids)
        view: Viewed | None = None  # a rosapi call under a namespace: its names mapped

        def on_result(result: ServiceResult) -> None:
            self.waiting -= 1
            timer = self._timers.pop(call_id, None)
            if timer is not None:
                timer.cancel()
            if result.ok and result.response is not None:
                data = result.response.data
                answer(True, data if view is None else view.tell(data))
            else:
                answer(False, result.error)

        self.waiting += 1
        try:
            name = session.resolve(op.service)
            view = viewed(session.graph, name, session.namespace)
            args = op.args if view is None else view.ask(op.args)
            pending = session.node.call_service(name, args, on_result)
        except MessageError as err:
            self.waiting -= 1
            answer(False, f"call_service: {err.prefixed('args')}")  # the answer says why
            return
        except GraphError as err:
            self.waiting -= 1
            answer(False, str(err))  # the answer says why; no status to repeat it
            return
        if pending.done:
            return
        timeout = config.service_timeout if op.timeout is None else float(op.timeout)
        if timeout > 0:

            def expire() -> None:
                self._timers.pop(call_id, None)
                if not pending.done:
                    pending.abandon()
                    on_result(
                        ServiceResult(
                            False,
                            None,
                            f"{session.resolve(op.service)} did not answer within {timeout:g} s",
                        )
                    )

            self._timers[call_id] = session.timers.call_later(timeout, expire)

    # -- providing -------------------------------------------------------------------------

    def advertise(self, op: AdvertiseService) -> None:
        config = self.session.config
        name = self.session.resolve(op.service)
        if name not in self.provided and len(self.provided) >= config.max_services:
            raise LimitError("advertised services", config.max_services)
        spelling = op.service

        def forward(call: ServiceCall) -> None:
            request_id = f"service_request:{spelling}:{next(self._ids)}"
            self.incoming[request_id] = call

            def forget() -> None:
                self.incoming.pop(request_id, None)

            call.on_abandon = forget
            self.session.send(
                {
                    "op": "call_service",
                    "id": request_id,
                    "service": spelling,
                    "args": call.request.data,
                }
            )

        self.provided[name] = self.session.node.provide_service(name, op.type, forward)
        self.session.report("info", f"advertised service {name}", op.id)

    def unadvertise(self, op: UnadvertiseService) -> None:
        name = self.session.resolve(op.service)
        service = self.provided.pop(name, None)
        if service is None:
            self.session.report(
                "warning",
                f"unadvertise_service: {op.service} is not advertised by this client",
                op.id,
            )
            return
        self._drop_calls_to(service)
        service.close()

    def respond(self, op: ServiceResponse) -> None:
        key = str(op.id) if op.id is not None else ""
        call = self.incoming.pop(key, None)
        if call is None:
            self.session.report(
                "warning",
                f"service_response: no call with id {op.id!r} is "
                "waiting (answered already, timed out, or never made)",
                op.id,
            )
            return
        if not op.result:
            call.fail(failure_text(op.values, f"{call.service.name} failed"))
            return
        values = op.values if op.values is not None else {}
        try:
            call.reply(values)
        except MessageError as err:
            raise err.prefixed("values") from None

    def _drop_calls_to(self, service: Service) -> None:
        for request_id, call in list(self.incoming.items()):
            if call.service is service:
                del self.incoming[request_id]

    def close(self) -> None:
        for timer in self._timers.values():
            timer.cancel()
        self._timers.clear()
        self.incoming.clear()
        for service in self.provided.values():
            service.close()
        self.provided.clear()
