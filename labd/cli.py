"""The ``labd`` command.

    labd serve [--host H] [--bridge-port P] [--data DIR] [--protected-prefix P ...]
               [--authorizer URL] [--tls-cert F --tls-key F] [--max-connections N]
               [--robot NAME=TASK ... | --no-robots]

    labd run PATH|URL [--task TASK] [--seed N] [--param NAME=VALUE] [--sandbox docker|bwrap]
             [--out DIR] [--json]              (labd.commands.run)

    labd submit | trials | show | download | rerun | cancel | export ...
                                               (labd.commands.remote: the HTTP API)
    labd users add NAME                        (labd.commands.users)
    labd demo                                  (labd.commands.demo: what make demo runs)
    labd worker --server URL                   (labd.commands.worker: a worker elsewhere)

``labd serve`` runs the bridge and its robots, the HTTP API (port 8080), the archive
(``--data``: SQLite and a folder by default) and its workers (``--workers``).
"""

from __future__ import annotations

import argparse
import asyncio
import ctypes
import logging
import signal
import sys
from collections.abc import Sequence
from pathlib import Path

from labd import __version__
from labd.commands import demo, fetching, remote, run, users, worker
from labd.config import DEFAULT_ROBOTS, BridgeConfig, LabConfig, RobotConfig
from labd.errors import LabError
from labd.lab import Lab
from labd.service import ServiceConfig
from labd.sim import registry
from labd.sim.params import parse_assignments
from scheduler.queue import QueueConfig
from scheduler.runner import RunOptions

log = logging.getLogger("labd")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="labd", description="The remote robot lab daemon.")
    parser.add_argument("--version", action="version", version=f"labd {__version__}")
    parser.add_argument(
        "--log-level", default="INFO", choices=["DEBUG", "INFO", "WARNING", "ERROR"]
    )
    commands = parser.add_subparsers(dest="command", required=True)

    serve = commands.add_parser(
        "serve",
        help="run the lab: the bridge and robots, the HTTP API, the archive and its workers",
    )
    defaults = BridgeConfig()
    serve.add_argument("--host", default=defaults.host, help="address to listen on")
    serve.add_argument(
        "--bridge-port",
        type=int,
        default=defaults.port,
        help="rosbridge WebSocket port (0: any free port)",
    )
    serve.add_argument("--data", type=Path, default=LabConfig().data, help="where data is kept")
    serve.add_argument(
        "--protected-prefix",
        action="append",
        dest="protected",
        help="names under this prefix never cross the bridge (repeatable; default /protected)",
    )
    serve.add_argument(
        "--authorizer",
        metavar="URL",
        help='require keys, checked at URL?key=KEY (answers {"seconds": N})',
    )
    serve.add_argument("--tls-cert", type=Path, help="certificate (PEM) to serve wss://")
    serve.add_argument("--tls-key", type=Path, help="private key (PEM) of --tls-cert")
    serve.add_argument("--max-connections", type=int, default=defaults.max_connections)
    serve.add_argument(
        "--robot",
        action="append",
        metavar="NAME=TASK",
        dest="robots",
        help="host a live robot running TASK at /robots/NAME (repeatable; "
        "default icreate-1=icreate-maze and pr2-1=pr2-table)",
    )
    serve.add_argument("--no-robots", action="store_true", help="host no robot")
    serve.add_argument(
        "--lockstep",
        action="store_true",
        help="robots step only when /lab/step is called (as in trials)",
    )
    serve.add_argument("--seed", type=int, default=0, help="the robots' first episode seed")
    serve.add_argument(
        "--param",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="a task parameter for every robot (repeatable)",
    )
    serve.add_argument("--no-playground", action="store_true", help="host no playground graph")
    service = serve.add_argument_group("the archive, the queue and its workers")
    service.add_argument("--http-port", type=int, default=8080, help="HTTP API port (0: any)")
    service.add_argument("--database", help="SQLAlchemy URL (default sqlite in --data)")
    service.add_argument(
        "--blobs", help="blob store: a folder or an fsspec URL such as s3://bucket/prefix"
    )
    service.add_argument(
        "--blobs-option",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="an fsspec storage option for --blobs, e.g. endpoint_url=http://127.0.0.1:9000 "
        "(repeatable; S3 keys come from AWS_ACCESS_KEY_ID and AWS_SECRET_ACCESS_KEY)",
    )
    service.add_argument(
        "--workers", type=int, default=1, help="trials run at once (default 1; 0: none)"
    )
    service.add_argument("--sandbox", choices=["docker", "bwrap"], help="default: docker if up")
    service.add_argument(
        "--lease", type=float, default=30.0, help="seconds before a silent worker's trial requeues"
    )
    fetching.add_options(service)
    service.add_argument(
        "--cache", type=Path, help="git mirrors and controller runtimes (default DATA/cache)"
    )
    service.add_argument("--no-service", action="store_true", help="no HTTP API, no workers")
    run.add_parser(commands)
    remote.add_parsers(commands)
    users.add_parser(commands)
    demo.add_parser(commands)
    worker.add_parser(commands)
    return parser


def robot_configs(args: argparse.Namespace) -> tuple[RobotConfig, ...]:
    if args.no_robots:
        return ()
    pairs = [(r.name, r.task) for r in DEFAULT_ROBOTS]
    if args.robots:
        pairs = []
        for item in args.robots:
            name, sep, task = item.partition("=")
            if not sep or not name or not task:
                raise SystemExit(f"labd serve: --robot takes NAME=TASK, got {item!r}")
            pairs.append((name, task))
    try:
        params = tuple(parse_assignments(args.param).items())
    except LabError as err:
        raise SystemExit(f"labd serve: --param {err}") from None
    robots = []
    for name, task in pairs:
        try:
            registry.validate(task, dict(params))
        except LabError as err:
            raise SystemExit(f"labd serve: robot {name}: {err}") from None
        robots.append(RobotConfig(name, task, params, args.seed, live=not args.lockstep))
    return tuple(robots)


def service_config(args: argparse.Namespace) -> ServiceConfig | None:
    if args.no_service:
        return None
    fetch = fetching.policy(args, "labd serve")
    return ServiceConfig(
        data=args.data,
        database=args.database,
        blobs=args.blobs,
        blob_options=_options(args.blobs_option),
        cache=args.cache,
        workers=args.workers,
        sandbox=args.sandbox,
        queue=QueueConfig(lease=args.lease),
        heartbeat=max(0.5, args.lease / 3),
        fetch=fetch,
        run=RunOptions(fetch=fetch),
    )


def _options(items: list[str]) -> dict[str, str]:
    options = {}
    for item in items:
        name, sep, value = item.partition("=")
        if not sep or not name:
            raise SystemExit(f"labd serve: --blobs-option takes NAME=VALUE, got {item!r}")
        options[name] = value
    return options


def bridge_config(args: argparse.Namespace) -> BridgeConfig:
    if (args.tls_cert is None) != (args.tls_key is None):
        raise SystemExit("labd serve: --tls-cert and --tls-key go together")
    protected = tuple(args.protected) if args.protected else BridgeConfig().protected_prefixes
    return BridgeConfig(
        host=args.host,
        port=args.bridge_port,
        protected_prefixes=protected,
        authorizer_url=args.authorizer,
        tls_cert=args.tls_cert,
        tls_key=args.tls_key,
        max_connections=args.max_connections,
    )


async def serve(config: LabConfig) -> None:
    """Run the lab until SIGINT or SIGTERM."""
    lab = Lab(config)
    await lab.start()
    bridge = lab.bridge
    print(f"labd {__version__}: rosbridge v2 on {bridge.url()}", flush=True)
    for name, robot in lab.robots.items():
        mode = "live" if robot.live else "lockstep"
        print(f"  robot {name} ({robot.sim.spec.name}, {mode}): {bridge.url(name)}", flush=True)
    if config.playground:
        print(f"  playground (no robot; clients meet here): {bridge.url('playground')}", flush=True)
    print(f"  {bridge.url()} serves the first of these.", flush=True)
    if lab.http is not None and lab.service is not None:
        print(f"HTTP API on {lab.http.url()}/api (OpenAPI: {lab.http.url()}/openapi.json)")
        print(f"  archive: {lab.service.config.database_url}, blobs {lab.service.store.url}")
        print(f"  workers: {len(lab.service.workers)}", flush=True)
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    try:
        await stop.wait()
    finally:
        await lab.close()


def return_freed_memory() -> None:
    """Have glibc give large freed buffers back to the system at once.

    Camera frames are allocations of about a megabyte; with glibc's default, the
    arena keeps them after they are freed and the server's footprint only grows
    (measured in bench/bridge.py: 270 MB instead of 120 MB). Elsewhere this does nothing.
    """
    try:
        libc = ctypes.CDLL("libc.so.6")
    except OSError:
        return
    m_mmap_threshold = -3
    libc.mallopt(m_mmap_threshold, 128 * 1024)


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(
        level=args.log_level,
        stream=sys.stderr,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    if args.command == "run":
        return run.main(args)
    if args.command in remote.COMMANDS:
        return remote.main(args)
    if args.command == "users":
        return users.main(args)
    if args.command == "demo":
        return demo.main(args)
    if args.command == "worker":
        return worker.main(args)
    if args.command == "serve":
        return_freed_memory()
        config = LabConfig(
            data=args.data,
            bridge=bridge_config(args),
            robots=robot_configs(args),
            playground=not args.no_playground,
            http_port=args.http_port,
            service=service_config(args),
        )
        asyncio.run(serve(config))
        return 0
    return 2


if __name__ == "__main__":
    sys.exit(main())
