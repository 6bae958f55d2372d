"""``labd worker --server URL``: run trials for a lab from another machine.

    labd worker --server URL [--token TOKEN] [--workers N] [--sandbox docker|bwrap]
                [--data DIR] [fetch options as for labd serve]

It claims trials from the lab's queue over the HTTP API, runs them here in the sandbox
(fetching the repositories itself, into ``DATA/cache``; the lab's own, the playground's,
from ``--server`` whatever public URL the lab records them under), uploads the MCAP
files and logs to the lab's archive and files the outcomes, until SIGINT or SIGTERM.
The token must be a worker's: ``labd users add NAME --worker`` on the lab's machine.
"""

from __future__ import annotations

import argparse
import asyncio
import os
import signal
import socket
from dataclasses import replace
from pathlib import Path
from typing import Any

import sandbox
from labd.commands import fetching, settings
from labd.commands.common import fail, json_option
from labd.errors import LabError
from labd.trial import LabHost, client_library
from repository.masking import mask_url
from sandbox.api import SandboxError
from scheduler.client import DEFAULT_SERVER
from scheduler.errors import RemoteError
from scheduler.fetch import FetchPolicy
from scheduler.remote import RemoteLab
from scheduler.runner import RunOptions
from scheduler.worker import Worker, WorkerConfig

DEFAULTS = WorkerConfig(name="", work=Path(), cache=Path())


def add_parser(commands: Any) -> None:
    p = commands.add_parser("worker", help="run a lab's queued trials on this machine")
    p.add_argument(
        "--server",
        default=os.environ.get("LABD_SERVER", DEFAULT_SERVER),
        help="the lab's HTTP address (default: $LABD_SERVER, else %(default)s)",
    )
    p.add_argument(
        "--token",
        default=os.environ.get("LABD_TOKEN"),
        help="a worker's token, from `labd users add NAME --worker` (default: $LABD_TOKEN)",
    )
    p.add_argument("--workers", type=int, default=1, help="trials run at once (default: 1)")
    p.add_argument(
        "--sandbox",
        choices=["docker", "bwrap"],
        help="isolation backend (default: docker if an engine answers, else bwrap)",
    )
    data = settings.get("data")
    settings.add(p, [replace(data, help="cache and work folders (default: {default})")])
    p.add_argument(
        "--cache",
        type=Path,
        help="mirrors and controller runtimes (default: DATA/cache)",
    )
    p.add_argument(
        "--heartbeat",
        type=float,
        default=DEFAULTS.heartbeat,
        help="seconds between heartbeats (default: %(default)g)",
    )
    p.add_argument(
        "--poll",
        type=float,
        default=DEFAULTS.poll,
        help="seconds between claims when idle (default: %(default)g)",
    )
    p.add_argument(
        "--canary",
        action="append",
        type=int,
        default=[],
        metavar="TRIAL",
        help="a reference trial to rerun at start and every --canary-every seconds; one"
        " that does not reproduce takes this worker out (repeatable; default: none)",
    )
    p.add_argument(
        "--canary-every",
        type=float,
        default=DEFAULTS.canary_every,
        help="seconds between canary reruns (default: %(default)g)",
    )
    json_option(p)
    fetching.add_options(p)


def main(args: argparse.Namespace) -> int:
    if not args.token:
        return fail(args, "give a worker's token (--token or LABD_TOKEN)")
    policy = fetching.policy(args, "labd worker")
    cache = (args.cache or args.data / "cache").resolve()
    work = (args.data / "work").resolve()
    work.mkdir(parents=True, exist_ok=True)
    try:
        backend = sandbox.backend(args.sandbox, cache, [client_library()])
    except (SandboxError, LabError) as err:
        return fail(args, str(err))
    lab = RemoteLab(args.server, args.token)
    try:
        lab.hello()
    except RemoteError as err:
        lab.close()
        return fail(args, str(err))
    policy = hosted(policy, args.server, lab.git)
    name = f"{socket.gethostname()}:{os.getpid()}"
    host = LabHost()
    workers = [
        Worker(
            lab,
            lab,
            backend,
            host,
            WorkerConfig(
                name=f"{name}/remote-{n + 1}",
                work=work,
                cache=cache,
                heartbeat=args.heartbeat,
                poll=args.poll,
                options=RunOptions(fetch=policy),
                # the lab replays what a worker elsewhere files; its own workers replay here
                replay=DEFAULTS.replay if lab.replays else 0.0,
                canaries=tuple(args.canary),
                canary_every=args.canary_every,
            ),
        )
        for n in range(args.workers)
    ]
    where = mask_url(args.server)
    print(f"labd worker: {len(workers)} worker(s) on {backend.name} for {where}", flush=True)
    try:
        asyncio.run(_run(workers))
    finally:
        lab.close()
    return 0


def hosted(policy: FetchPolicy, server: str, public: str | None) -> FetchPolicy:
    """``policy`` with the lab's own repositories (the playground's): recorded under
    ``public`` (``PUBLIC/git``, as the lab's hello says) or under ``server``'s ``/git/``,
    and fetched from ``server``'s, over its HTTP port like its API. A worker that reaches
    the lab at another address than the public one (a compose network's ``lab:8080``)
    runs them all the same, and whatever the lab says, fetches them from no other host."""
    own = f"{server.rstrip('/')}/git/"
    prefixes = [own] if public is None else [f"{public.rstrip('/')}/", own]
    return replace(policy, hosted=tuple(dict.fromkeys(prefixes)), hosted_at=own)


async def _run(workers: list[Worker]) -> None:
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    tasks = [asyncio.create_task(w.run(stop)) for w in workers]
    await stop.wait()
    for task in tasks:  # a trial under way is abandoned: its lease runs out and it requeues
        task.cancel()
    await asyncio.gather(*tasks, return_exceptions=True)
