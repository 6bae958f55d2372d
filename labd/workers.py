"""Worker processes: ``labd serve --worker-processes N`` runs trials in N child processes.

A worker in the service's own process (``--workers``) shares its interpreter with the
lab side of every other trial running there: the physics, the bridge and the recorder of
two trials take turns on one interpreter lock, however many cores the machine has. A
worker process is ``labd worker`` (``labd.commands.worker``: the same ``Worker``) started
by the service against its own HTTP API, so each trial's lab side has a process, and a
core, of its own; what it files is held to its record by the lab, as any remote
worker's.

Each start of the service makes a worker token for the account ``LOCAL_WORKERS``
(revoking that account's earlier tokens) and hands it to its children in their
environment, never on a command line. A child reaches the lab directly, never through a
proxy the lab's environment names (``NO_PROXY``). A child that dies is started again
after a pause (the lab's lease gives its trial to another worker); when the service
stops, its children are asked to stop (SIGTERM: they hand their trials back to the
queue) and killed if they have not within ``STOP_SECONDS``.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import signal
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from urllib.parse import urlsplit

from repository.accounts import Accounts
from repository.errors import RecordNotFound

log = logging.getLogger("labd.workers")
LOCAL_WORKERS = "local-workers"  # the account the service's worker processes use
STOP_SECONDS = 20.0
RESTART_SECONDS = 5.0  # between a child's death and its next start


def direct(server: str, environ: Mapping[str, str]) -> dict[str, str]:
    """``NO_PROXY`` and ``no_proxy`` (``environ``'s, with ``server``'s host added): a
    child calls the lab, and fetches its repositories, directly, whatever proxy the lab's
    environment names for the world (httpx reads either variable, curl and so git both)."""
    listed = [environ.get("NO_PROXY", ""), environ.get("no_proxy", ""), urlsplit(server).hostname]
    hosts = [h.strip() for item in listed if item for h in item.split(",") if h.strip()]
    joined = ",".join(dict.fromkeys(hosts))
    return {"NO_PROXY": joined, "no_proxy": joined}


class WorkerProcesses:
    """``count`` children running ``labd worker`` against this lab."""

    def __init__(
        self,
        accounts: Accounts,
        data: Path,
        count: int,
        *,
        cache: Path | None = None,
        heartbeat: float = 10.0,
        sandbox: str | None = None,
        options: Sequence[str] = (),
        poll: float = 0.5,
    ) -> None:
        self.accounts = accounts
        self.data = data
        self.cache = cache
        self.heartbeat = heartbeat
        self.count = count
        self.sandbox = sandbox
        self.options = tuple(options)  # more ``labd worker`` options (what it may fetch)
        self.poll = poll
        self.children: list[asyncio.subprocess.Process | None] = [None] * count
        self._tasks: list[asyncio.Task[None]] = []
        self._stopping = False

    def token(self) -> str:
        """A new worker token for ``LOCAL_WORKERS``; the earlier ones are revoked."""
        try:
            self.accounts.index.user(LOCAL_WORKERS)
        except RecordNotFound:
            return self.accounts.index.add_user(LOCAL_WORKERS, worker=True)
        self.accounts.revoke_all(LOCAL_WORKERS)
        return self.accounts.new_token(LOCAL_WORKERS, f"worker processes of pid {os.getpid()}")[1]

    async def start(self, server: str, env: dict[str, str] | None = None) -> None:
        """Start the children against ``server`` (this lab's HTTP address), with ``env``
        added to their environment. The lab's own ``LABD_*`` settings are not theirs: a
        child takes what it runs from its command line."""
        token = await asyncio.to_thread(self.token)
        base = {k: v for k, v in os.environ.items() if not k.startswith("LABD_")}
        environ = {**base, **(env or {}), "LABD_TOKEN": token, **direct(server, base)}
        for n in range(self.count):
            task = asyncio.create_task(self._keep(n, server, environ), name=f"worker process {n}")
            self._tasks.append(task)
        log.info("%d worker process(es) for %s", self.count, server)

    def argv(self, server: str) -> list[str]:
        argv = [sys.executable, "-m", "labd", "worker", "--server", server, "--workers", "1"]
        argv += ["--data", str(self.data), "--poll", f"{self.poll:g}"]
        argv += ["--heartbeat", f"{self.heartbeat:g}"]
        if self.cache is not None:
            argv += ["--cache", str(self.cache)]
        if self.sandbox is not None:
            argv += ["--sandbox", self.sandbox]
        return argv + list(self.options)

    async def _keep(self, n: int, server: str, env: dict[str, str]) -> None:
        """Run child ``n``, and again whenever it ends, until the service stops."""
        while not self._stopping:
            child = await asyncio.create_subprocess_exec(
                *self.argv(server), env=env, stdin=asyncio.subprocess.DEVNULL
            )
            self.children[n] = child
            code = await child.wait()
            self.children[n] = None
            if self._stopping:
                return
            log.error(
                "worker process %d (pid %d) ended with status %s; starting it again in %g s",
                n + 1,
                child.pid,
                code,
                RESTART_SECONDS,
            )
            await asyncio.sleep(RESTART_SECONDS)

    async def close(self) -> None:
        """Ask the children to stop, and wait for them (killing those that do not)."""
        self._stopping = True
        children = [c for c in self.children if c is not None and c.returncode is None]
        for child in children:
            with contextlib.suppress(ProcessLookupError):
                child.send_signal(signal.SIGTERM)
        for child in children:
            try:
                await asyncio.wait_for(child.wait(), STOP_SECONDS)
            except TimeoutError:
                log.error("worker process %d did not stop; killing it", child.pid)
                with contextlib.suppress(ProcessLookupError):
                    child.kill()
                await child.wait()
        for task in self._tasks:
            task.cancel()
        for task in self._tasks:
            with contextlib.suppress(asyncio.CancelledError):
                await task
