"""Lean rosbridge clients for ``bench/bridge.py``, one per process.

The clients speak WebSocket themselves on an ``asyncio.Protocol`` (handshake,
framing, ping/pong) so that a message costs them a couple of microseconds and the
server under test stays the bottleneck: publish frames are formatted from a byte
template, masked with websockets' C ``apply_mask`` and written in batches under
flow control; the subscriber splits frames by hand and parses their JSON with orjson.

    python bench/clients.py sub --url URL --kind twist|image [--mode count|latency|stall]
    python bench/clients.py pub --url URL --kind twist|image --rate HZ --seconds S

The subscriber subscribes, then publishes a probe on the topic and waits to receive
it back, so its subscription is known to be live; then it prints ``ready``. In
``stall`` mode it then stops reading its socket for good (TCP backpressure builds up
in the server) until SIGTERM. The publisher prints ``go`` when it starts, publishes
for ``--seconds`` (``--rate 0``: as fast as the server takes them), then one end
marker. Both print one JSON line of results last.

Each message carries its sequence number and its ``time.perf_counter()`` at sending
(Twist: ``linear.y`` and ``linear.x``; Image: ``header.stamp.sec`` and
``header.frame_id``). ``perf_counter`` is CLOCK_MONOTONIC on Linux, shared by all
processes, so the subscriber's receive time minus the send time is the latency.
"""

from __future__ import annotations

import argparse
import asyncio
import base64
import contextlib
import os
import random
import signal
import struct
import sys
import time
from collections.abc import Callable
from urllib.parse import urlsplit

import orjson
from websockets.frames import apply_mask  # the C version when websockets has it
from websockets.utils import accept_key

OP_CONT, OP_TEXT, OP_BINARY, OP_CLOSE, OP_PING, OP_PONG = 0x0, 0x1, 0x2, 0x8, 0x9, 0xA
BATCH = 64  # frames per write when publishing unpaced
READ_PAUSE = 0.002  # seconds between reads when counting (not when timing) messages
HIST_STEP = 0.01  # seconds per bucket of the arrival histogram

TYPES = {"twist": "geometry_msgs/msg/Twist", "image": "sensor_msgs/msg/Image"}
TWIST = (
    b'{"op":"publish","topic":%b,"msg":{"linear":{"x":%b,"y":%d.0,"z":0.0},'
    b'"angular":{"x":0.0,"y":0.0,"z":0.5}}}'
)
IMAGE = (
    b'{"op":"publish","topic":%b,"msg":{"header":{"stamp":{"sec":%d,"nanosec":0},'
    b'"frame_id":"%b"},"height":%d,"width":%d,"encoding":"rgb8","is_bigendian":0,'
    b'"step":%d,"data":"%b"}}'
)
END, PROBE = -1, -2  # Twist sequence numbers of the markers

_randbytes = random.Random().randbytes  # masking keys need no cryptographic strength here


def encode(payload: bytes, opcode: int = OP_TEXT) -> bytes:
    """One masked client frame."""
    n = len(payload)
    if n < 126:
        head = bytes((0x80 | opcode, 0x80 | n))
    elif n < 65536:
        head = struct.pack("!BBH", 0x80 | opcode, 0xFE, n)
    else:
        head = struct.pack("!BBQ", 0x80 | opcode, 0xFF, n)
    mask = _randbytes(4)
    return head + mask + apply_mask(payload, mask)


class WsClient(asyncio.Protocol):
    """A minimal WebSocket client connection; calls ``on_frame(payload, t)`` per message."""

    def __init__(self, on_frame: Callable[[bytes, float], None]) -> None:
        loop = asyncio.get_running_loop()
        self.on_frame = on_frame
        self.transport: asyncio.Transport | None = None
        self.opened: asyncio.Future[None] = loop.create_future()
        self.closed: asyncio.Future[None] = loop.create_future()
        self._writable = asyncio.Event()
        self._writable.set()
        self._key = base64.b64encode(os.urandom(16))
        self._head = b""  # the HTTP response, until the handshake is done
        self._pending: list[bytes] = []  # an incomplete frame
        self._have = 0
        self._need = 0
        self._parts: list[bytes] = []  # a fragmented message
        self._closing = False
        # Seconds to stop reading after each read, so that reads come in batches: a
        # subscriber that only counts then costs less per message than one wake-up each.
        self.read_pause = 0.0

    @classmethod
    async def connect(cls, url: str, on_frame: Callable[[bytes, float], None]) -> WsClient:
        parts = urlsplit(url)
        host, port = parts.hostname or "127.0.0.1", parts.port or 80
        loop = asyncio.get_running_loop()
        _, client = await loop.create_connection(lambda: cls(on_frame), host, port)
        assert client.transport is not None
        client.transport.write(
            b"GET %b HTTP/1.1\r\nHost: %b:%d\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
            b"Sec-WebSocket-Key: %b\r\nSec-WebSocket-Version: 13\r\n\r\n"
            % ((parts.path or "/").encode(), host.encode(), port, client._key)
        )
        await asyncio.wait_for(client.opened, 10)
        return client

    # asyncio.Protocol
    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self.transport = transport

    def connection_lost(self, exc: Exception | None) -> None:
        self._writable.set()
        if not self.opened.done():
            self.opened.set_exception(ConnectionError("closed during the handshake"))
        if not self.closed.done():
            self.closed.set_result(None)

    def pause_writing(self) -> None:
        self._writable.clear()

    def resume_writing(self) -> None:
        self._writable.set()

    def data_received(self, data: bytes) -> None:
        t = time.perf_counter()
        if not self.opened.done():
            data = self._handshake(data)
            if not data:
                return
        if self._pending:
            self._pending.append(data)
            self._have += len(data)
            if self._have < self._need:
                return
            data = b"".join(self._pending)
            self._pending = []
        off, end = 0, len(data)
        while end - off >= 2:
            n = data[off + 1] & 0x7F
            hdr = 2
            if n == 126:
                hdr = 4
                n = int.from_bytes(data[off + 2 : off + 4]) if end - off >= 4 else -1
            elif n == 127:
                hdr = 10
                n = int.from_bytes(data[off + 2 : off + 10]) if end - off >= 10 else -1
            if n < 0 or end - off < hdr + n:
                break
            self._frame(data[off], data[off + hdr : off + hdr + n], t)
            off += hdr + n
        if off < end:
            rest = data[off:]
            self._pending = [rest]
            self._have = len(rest)
            self._need = self._frame_size(rest)
        if self.read_pause and self.transport is not None and not self.transport.is_closing():
            self.transport.pause_reading()
            asyncio.get_running_loop().call_later(self.read_pause, self._resume_reading)

    def _resume_reading(self) -> None:
        if self.transport is not None and not self.transport.is_closing():
            self.transport.resume_reading()

    @staticmethod
    def _frame_size(head: bytes) -> int:
        if len(head) < 2:
            return 2
        n = head[1] & 0x7F
        if n < 126:
            return 2 + n
        hdr = 4 if n == 126 else 10
        if len(head) < hdr:
            return hdr
        return hdr + int.from_bytes(head[2:hdr])

    def _handshake(self, data: bytes) -> bytes:
        self._head += data
        head, sep, rest = self._head.partition(b"\r\n\r\n")
        if not sep:
            return b""
        lines = head.split(b"\r\n")
        headers = dict(line.lower().split(b": ", 1) for line in lines[1:] if b": " in line)
        accept = accept_key(self._key.decode()).lower().encode()
        if b" 101 " not in lines[0] or headers.get(b"sec-websocket-accept") != accept:
            self.opened.set_exception(ConnectionError(lines[0].decode(errors="replace")))
            assert self.transport is not None
            self.transport.close()
            return b""
        self.opened.set_result(None)
        return rest

    def _frame(self, first: int, payload: bytes, t: float) -> None:
        opcode = first & 0x0F
        fin = first & 0x80
        if opcode in (OP_TEXT, OP_BINARY) and fin:
            self.on_frame(payload, t)
        elif opcode in (OP_TEXT, OP_BINARY, OP_CONT):
            self._parts.append(payload)
            if fin:
                whole, self._parts = b"".join(self._parts), []
                self.on_frame(whole, t)
        elif opcode == OP_PING:
            self.write(encode(payload, OP_PONG))
        elif opcode == OP_CLOSE:
            if not self._closing:
                self._closing = True
                self.write(encode(payload[:2], OP_CLOSE))
            assert self.transport is not None
            self.transport.close()

    # sending
    def write(self, data: bytes) -> None:
        assert self.transport is not None
        if not self.transport.is_closing():
            self.transport.write(data)

    def send(self, frame: dict[str, object] | bytes) -> None:
        self.write(encode(frame if isinstance(frame, bytes) else orjson.dumps(frame)))

    async def drain(self) -> None:
        if not self._writable.is_set():
            await self._writable.wait()
        if self.closed.done():
            raise ConnectionError("the server closed the connection")

    async def flush(self) -> None:
        """Wait until everything written has left for the kernel."""
        assert self.transport is not None
        while self.transport.get_write_buffer_size() and not self.closed.done():
            await asyncio.sleep(0.005)

    async def close(self) -> None:
        if not self._closing and not self.closed.done():
            self._closing = True
            self.write(encode(struct.pack("!H", 1000), OP_CLOSE))
        with contextlib.suppress(asyncio.TimeoutError):
            await asyncio.wait_for(asyncio.shield(self.closed), 2)
        assert self.transport is not None
        self.transport.abort()


# -- messages ---------------------------------------------------------------------------


class Messages:
    """Builds the publish frames of one kind and reads them back."""

    def __init__(self, kind: str, topic: str, width: int = 640, height: int = 480) -> None:
        self.kind = kind
        self.topic_json = orjson.dumps(topic)
        self.width, self.height = width, height
        self.data = base64.b64encode(os.urandom(width * height * 3))
        self._probe_data = base64.b64encode(bytes(3))

    def publish(self, seq: int, t: float) -> bytes:
        if self.kind == "twist":
            return TWIST % (self.topic_json, repr(t).encode(), seq)
        w, h = self.width, self.height
        return IMAGE % (self.topic_json, seq, repr(t).encode(), h, w, w * 3, self.data)

    def marker(self, which: int) -> bytes:
        if self.kind == "twist":
            return TWIST % (self.topic_json, b"0.0", which)
        name = b"end" if which == END else b"probe"
        return IMAGE % (self.topic_json, 0, name, 1, 1, 3, self._probe_data)

    def read(self, payload: bytes) -> tuple[int, float]:
        """(sequence number or END or PROBE, send time) of a publish frame."""
        msg = orjson.loads(payload)["msg"]
        if self.kind == "twist":
            linear = msg["linear"]
            return int(linear["y"]), linear["x"]
        header = msg["header"]
        frame_id = header["frame_id"]
        if frame_id == "end":
            return END, 0.0
        if frame_id == "probe":
            return PROBE, 0.0
        return header["stamp"]["sec"], float(frame_id)


# -- subscriber -------------------------------------------------------------------------


class Subscriber:
    def __init__(self, messages: Messages, mode: str) -> None:
        loop = asyncio.get_running_loop()
        self.messages = messages
        self.latency = mode == "latency"
        self.probed: asyncio.Future[None] = loop.create_future()
        self.ended: asyncio.Future[None] = loop.create_future()
        self.received = 0
        self.other = 0  # frames that are not this topic's messages
        self.base = 0.0
        self.hist: list[int] = []
        self.samples: list[tuple[float, float]] = []  # (send time, latency)

    def on_frame(self, payload: bytes, t: float) -> None:
        try:
            seq, sent = self.messages.read(payload)
        except (orjson.JSONDecodeError, KeyError, TypeError, ValueError):
            self.other += 1
            return
        if seq >= 0:
            if not self.probed.done():
                return  # an earlier run's leftover
            self.received += 1
            i = int((t - self.base) / HIST_STEP)
            hist = self.hist
            if i >= len(hist):
                hist.extend([0] * (i + 1 - len(hist)))
            hist[i] += 1
            if self.latency:
                self.samples.append((sent, t - sent))
        elif seq == PROBE:
            if not self.probed.done():
                self.probed.set_result(None)
        elif seq == END and self.probed.done() and not self.ended.done():
            self.ended.set_result(None)


async def run_subscriber(args: argparse.Namespace) -> dict[str, object]:
    messages = Messages(args.kind, args.topic, args.width, args.height)
    sub = Subscriber(messages, args.mode)
    client = await WsClient.connect(args.url, sub.on_frame)
    kind = TYPES[args.kind]
    client.send({"op": "subscribe", "id": "bench", "topic": args.topic, "type": kind})
    client.send({"op": "advertise", "id": "bench", "topic": args.topic, "type": kind})
    client.send(messages.marker(PROBE))
    await asyncio.wait_for(sub.probed, 10)
    sub.base = time.perf_counter()
    cpu0 = time.process_time()
    if args.mode == "count":
        client.read_pause = READ_PAUSE
    print("ready", flush=True)

    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    loop.add_signal_handler(signal.SIGTERM, stop.set)
    stopped = asyncio.ensure_future(stop.wait())
    if args.mode == "stall":
        assert client.transport is not None
        client.transport.pause_reading()
        await asyncio.wait([stopped, client.closed], return_when=asyncio.FIRST_COMPLETED)
        client.transport.abort()
        return {"stalled": True, "closed_by_server": client.closed.done() and not stop.is_set()}
    await asyncio.wait([stopped, sub.ended, client.closed], return_when=asyncio.FIRST_COMPLETED)
    cpu = time.process_time() - cpu0
    wall = time.perf_counter() - sub.base
    stopped.cancel()
    await client.close()
    return {
        "received": sub.received,
        "other": sub.other,
        "end_seen": sub.ended.done(),
        "base": sub.base,
        "hist_step": HIST_STEP,
        "hist": sub.hist,
        "samples": [(round(s, 6), round(lat, 7)) for s, lat in sub.samples],
        "cpu": cpu,
        "wall": wall,
    }


# -- publisher --------------------------------------------------------------------------


async def run_publisher(args: argparse.Namespace) -> dict[str, object]:
    messages = Messages(args.kind, args.topic, args.width, args.height)
    client = await WsClient.connect(args.url, lambda payload, t: None)
    client.send({"op": "advertise", "id": "bench", "topic": args.topic, "type": TYPES[args.kind]})
    publish = messages.publish
    clock = time.perf_counter
    cpu0 = time.process_time()
    print("go", flush=True)
    start = clock()
    deadline = start + args.seconds
    seq = 0
    if args.rate <= 0:  # as fast as the server takes them
        while clock() < deadline:
            client.write(b"".join([encode(publish(seq + i, clock())) for i in range(BATCH)]))
            seq += BATCH
            await client.drain()
            await asyncio.sleep(0)  # let pings and the close in
    else:
        period = 1.0 / args.rate
        while (due := start + seq * period) < deadline:
            await asyncio.sleep(max(0.0, due - clock()))
            client.write(encode(publish(seq, clock())))
            seq += 1
            await client.drain()
    end = clock()
    client.write(encode(messages.marker(END)))
    await client.flush()
    cpu = time.process_time() - cpu0
    await client.close()
    return {"sent": seq, "start": start, "end": end, "cpu": cpu}


def main() -> None:
    parser = argparse.ArgumentParser(description="a benchmark client of bench/bridge.py")
    parser.add_argument("role", choices=["pub", "sub"])
    parser.add_argument("--url", required=True)
    parser.add_argument("--kind", choices=sorted(TYPES), default="twist")
    parser.add_argument("--topic", default="/cmd_vel")
    parser.add_argument("--mode", choices=["count", "latency", "stall"], default="count")
    parser.add_argument("--rate", type=float, default=0.0, help="messages per second; 0: max")
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=480)
    args = parser.parse_args()
    run = run_publisher if args.role == "pub" else run_subscriber
    result = asyncio.run(run(args))
    sys.stdout.write(orjson.dumps(result).decode() + "\n")


if __name__ == "__main__":
    main()
