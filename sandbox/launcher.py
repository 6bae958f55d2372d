"""The first process of every sandboxed job; standard library only, copied into the runtime.

Both backends start it as pid 1 of the job's own pid and network namespaces:

    python -I -S /opt/labd/launcher.py [--bridge SOCKET [--port N]] [--cwd DIR]
                                       [--mkdir DIR]... -- CMD...

1. With ``--bridge``, it listens on 127.0.0.1:N (9090 by default; the only address there
   is) and relays every connection, byte for byte, to the host's unix socket mounted at
   SOCKET: a controller's to the trial's bridge, a build step's (port 3128) to the lab's
   proxy to the registry. The relay is a pair of asyncio protocols that write what they
   read at once (no buffering of their own; TCP_NODELAY is asyncio's default), so a
   lockstep controller pays two local socket hops per message.
2. It runs CMD in its own session with the working directory DIR, its environment passed
   on as is (the backend composes it), and standard streams inherited.
3. It forwards SIGTERM, SIGINT and SIGHUP to CMD's process group, reaps every orphan (it
   is pid 1), and when CMD ends, lets the relays pass on what they hold (a second at
   most), then exits with CMD's status, or 128+N when CMD died of signal N. When it
   exits, the kernel ends every process left in the namespace.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import os
import signal
import subprocess
import sys
from collections.abc import Sequence

BRIDGE_HOST = "127.0.0.1"
BRIDGE_PORT = 9090
FORWARDED = (signal.SIGTERM, signal.SIGINT, signal.SIGHUP)
FLUSH_SECONDS = 1.0  # at the end, how long open relays may take to pass on what they hold


class _Relays:
    """The relayed connections that are open, so that they can finish when the job does."""

    def __init__(self, bridge: str) -> None:
        self.bridge = bridge
        self.open: set[_Side] = set()
        self.tasks: set[asyncio.Task[None]] = set()
        self.idle = asyncio.Event()
        self.idle.set()

    def opened(self, side: _Side) -> None:
        self.open.add(side)
        self.idle.clear()

    def closed(self, side: _Side) -> None:
        self.open.discard(side)
        if not self.open:
            self.idle.set()


class _Side(asyncio.Protocol):
    """One end of a relayed connection: what it reads, its peer writes."""

    def __init__(self, relays: _Relays) -> None:
        self.relays = relays
        self.transport: asyncio.Transport | None = None
        self.peer: _Side | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self.transport = transport
        self.relays.opened(self)

    def data_received(self, data: bytes) -> None:
        if self.peer is not None and self.peer.transport is not None:
            self.peer.transport.write(data)

    def eof_received(self) -> bool:
        # WebSocket needs no half-closed connections: close both ends, flushing first.
        self._close_peer()
        return False

    def connection_lost(self, exc: Exception | None) -> None:
        self._close_peer()
        self.relays.closed(self)

    def pause_writing(self) -> None:
        if self.peer is not None and self.peer.transport is not None:
            self.peer.transport.pause_reading()

    def resume_writing(self) -> None:
        if self.peer is not None and self.peer.transport is not None:
            self.peer.transport.resume_reading()

    def _close_peer(self) -> None:
        if self.peer is not None and self.peer.transport is not None:
            self.peer.transport.close()


class _Inbound(_Side):
    """A connection from inside the sandbox; its peer is a new connection to the bridge."""

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        super().connection_made(transport)
        assert self.transport is not None
        self.transport.pause_reading()  # until the bridge side is there to write to
        task = asyncio.get_running_loop().create_task(self._connect())
        self.relays.tasks.add(task)
        task.add_done_callback(self.relays.tasks.discard)

    async def _connect(self) -> None:
        assert self.transport is not None
        loop = asyncio.get_running_loop()
        try:
            _, outbound = await loop.create_unix_connection(
                lambda: _Side(self.relays), self.relays.bridge
            )
        except OSError as err:
            sys.stderr.write(f"labd-launcher: cannot reach {self.relays.bridge}: {err}\n")
            self.transport.abort()
            return
        self.peer, outbound.peer = outbound, self
        if self.transport.is_closing():
            self._close_peer()
        else:
            self.transport.resume_reading()


class Launcher:
    """Relay, child, signals and exit status of one job."""

    def __init__(self, command: Sequence[str], cwd: str, bridge: str | None, port: int) -> None:
        self.command = list(command)
        self.cwd = cwd
        self.bridge = bridge
        self.port = port
        self._child: subprocess.Popen[bytes] | None = None
        self._status: asyncio.Future[int] | None = None

    async def run(self) -> int:
        loop = asyncio.get_running_loop()
        self._status = loop.create_future()
        server = relays = None
        if self.bridge is not None:
            relays = _Relays(self.bridge)
            server = await loop.create_server(lambda: _Inbound(relays), BRIDGE_HOST, self.port)
        loop.add_signal_handler(signal.SIGCHLD, self._reap)
        for signum in FORWARDED:
            loop.add_signal_handler(signum, self._forward, signum)
        try:
            self._child = subprocess.Popen(  # noqa: S603 - running it is the point
                self.command, cwd=self.cwd, start_new_session=True
            )
        except OSError as err:
            sys.stderr.write(f"labd-launcher: cannot run {self.command[0]!r}: {err}\n")
            return 127 if isinstance(err, FileNotFoundError) else 126
        self._reap()  # in case it ended before the handler saw it
        status = await self._status
        if server is not None and relays is not None:
            server.close()
            # What the controller sent just before it ended still reaches the bridge.
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(relays.idle.wait(), FLUSH_SECONDS)
        self._kill_group()
        return status

    def _reap(self) -> None:
        """Collect every ended child: the controller, and orphans handed to pid 1."""
        while True:
            try:
                pid, status = os.waitpid(-1, os.WNOHANG)
            except ChildProcessError:
                return
            if pid == 0:
                return
            if self._child is not None and pid == self._child.pid:
                self._child.returncode = os.waitstatus_to_exitcode(status)
                code = self._child.returncode
                assert self._status is not None
                if not self._status.done():
                    self._status.set_result(code if code >= 0 else 128 - code)

    def _forward(self, signum: int) -> None:
        if self._child is not None and self._child.returncode is None:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(self._child.pid, signum)

    def _kill_group(self) -> None:
        """End what the controller left behind (the namespace's end would, too)."""
        if self._child is not None:
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.killpg(self._child.pid, signal.SIGKILL)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="labd-launcher")
    parser.add_argument("--bridge", help="the bridge's unix socket")
    parser.add_argument("--port", type=int, default=BRIDGE_PORT)
    parser.add_argument("--cwd", default="/code")
    parser.add_argument("--mkdir", action="append", default=[], help="make this folder first")
    parser.add_argument("command", nargs="+")
    args = parser.parse_args(argv)
    # Whatever the backend's tools left open stays out of the job.
    os.closerange(3, 1 << 16)
    for folder in args.mkdir:
        os.makedirs(folder, exist_ok=True)
    launcher = Launcher(args.command, args.cwd, args.bridge, args.port)
    return asyncio.run(launcher.run())


if __name__ == "__main__":
    sys.exit(main())
