"""The ceiling for ``bench/bridge.py``: a bare ``websockets`` relay with orjson.

It understands just enough rosbridge to be driven by the same clients as labd:
``subscribe`` and ``unsubscribe`` register a connection for a topic, and each
``publish`` frame is parsed with orjson, re-serialised, and sent to every connection
subscribed to its topic (the sender included, as rosbridge does). Everything else is
ignored. No validation, no queues, no types: whatever labd does on top of this is
what its ratio to this relay measures.

    python bench/relay.py [--host H] [--port P]    # port 0: any free port

prints ``relay on ws://HOST:PORT`` once it listens, and runs until SIGTERM or SIGINT.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import signal

import orjson
from websockets.asyncio.server import ServerConnection, serve
from websockets.exceptions import ConnectionClosed

MAX_SIZE = 64 * 1024 * 1024  # labd's max_frame_size


class Relay:
    def __init__(self) -> None:
        self.topics: dict[str, set[ServerConnection]] = {}

    async def handle(self, ws: ServerConnection) -> None:
        mine: set[str] = set()
        try:
            with contextlib.suppress(ConnectionClosed):
                while True:
                    await self.receive(ws, mine, await ws.recv(decode=False))
        finally:
            for topic in mine:
                self.topics[topic].discard(ws)

    async def receive(self, ws: ServerConnection, mine: set[str], data: bytes | str) -> None:
        try:
            frame = orjson.loads(data)
            op, topic = frame["op"], frame["topic"]
        except (orjson.JSONDecodeError, KeyError, TypeError):
            return
        if op == "publish":
            subscribers = self.topics.get(topic)
            if subscribers:
                out = orjson.dumps(frame)
                for conn in tuple(subscribers):
                    with contextlib.suppress(ConnectionClosed):
                        await conn.send(out, text=True)
        elif op == "subscribe":
            self.topics.setdefault(topic, set()).add(ws)
            mine.add(topic)
        elif op == "unsubscribe" and topic in mine:
            self.topics[topic].discard(ws)
            mine.discard(topic)


async def main(host: str, port: int) -> None:
    relay = Relay()
    async with serve(relay.handle, host, port, compression=None, max_size=MAX_SIZE) as server:
        bound = server.sockets[0].getsockname()[1]
        print(f"relay on ws://{host}:{bound}", flush=True)
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, stop.set)
        await stop.wait()


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--host", default="127.0.0.1")
    parser.add_argument("--port", type=int, default=0)
    args = parser.parse_args()
    asyncio.run(main(args.host, args.port))
