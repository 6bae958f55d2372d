"""``labd serve``: the lab. The bridge and its robots, the HTTP API, the archive, workers.

    labd serve [--host H] [--bridge-port P] [--http-port P] [--data DIR]
               [--robot NAME=TASK ... | --no-robots] [--lockstep] [--no-service] ...

Every default comes from the configuration objects (``labd.config``,
``labd.service``); ``labd serve --help`` shows them. A port in use, a certificate
that does not load, an index of an older schema: each stops it with one line saying
what to change.
"""

from __future__ import annotations

import argparse
import asyncio
import ctypes
import ipaddress
import logging
import resource
import signal
import sys
from dataclasses import replace
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

from labd import __version__, privacy
from labd.commands import fetching
from labd.commands.common import assignment, fail, param_option
from labd.config import BridgeConfig, DriveLimits, HttpConfig, RobotConfig
from labd.datalock import DataLock
from labd.errors import LabError
from labd.lab import Lab, LabConfig
from labd.service import ServiceConfig
from labd.sim import registry
from labd.videos import MODES
from repository.errors import ArchiveError, SchemaMismatch
from repository.masking import mask_url
from repository.reservations import MAX_HORIZON, MAX_SLOT, Rules
from repository.units import KiB, MiB
from sandbox.api import SandboxError
from scheduler.data import DataPolicy
from scheduler.evaluate import HeldOutBudget
from scheduler.queue import QueueConfig
from scheduler.runner import RunOptions

log = logging.getLogger("labd.serve")
# Seconds a thread holding the interpreter keeps it while another waits. The robots'
# loop shares the interpreter with the pages' thread and the threads of uploads and
# exports; during a 1 GiB upload the camera went up to 0.85 s without a frame at
# Python's default (5 ms), 0.08-0.76 s at 1 ms on a loaded machine (docs/faults.md).
SWITCH_INTERVAL = 0.001
BRIDGE = BridgeConfig()
DRIVES = DriveLimits()
HTTP = HttpConfig()
LAB = LabConfig()
SERVICE = ServiceConfig()
RULES = Rules()


class Refused(Exception):
    """A combination of options that cannot run; the message says what to change."""


def add_parser(commands: Any) -> None:
    serve = commands.add_parser(
        "serve",
        help="run the lab: the bridge and robots, the HTTP API, the archive and its workers",
    )
    serve.add_argument(
        "--host", default=BRIDGE.host, help="address to listen on (default: %(default)s)"
    )
    serve.add_argument(
        "--bridge-port",
        type=int,
        default=BRIDGE.port,
        help="rosbridge WebSocket port (default: %(default)s; 0: any free port)",
    )
    serve.add_argument(
        "--data", type=Path, default=LAB.data, help="where data is kept (default: %(default)s)"
    )
    serve.add_argument(
        "--protected-prefix",
        action="append",
        dest="protected",
        help="names under this prefix never cross the bridge (repeatable; default: "
        f"{' '.join(BRIDGE.protected_prefixes)})",
    )
    serve.add_argument(
        "--authorizer",
        metavar="URL",
        help='require keys, checked at URL?key=KEY (answers {"seconds": N}; default: none)',
    )
    serve.add_argument(
        "--key-recheck",
        type=float,
        default=BRIDGE.key_recheck,
        metavar="S",
        help="seconds between asking the authorizer again about each connected client's"
        " key: a withdrawn key disconnects its client within this (default: %(default)g;"
        " 0: never)",
    )
    serve.add_argument(
        "--tls-cert",
        type=Path,
        help="certificate (PEM): the robots are served at wss://, the pages and API at"
        " https:// (their cookies marked Secure) (default: none, plain ws:// and http://)",
    )
    serve.add_argument("--tls-key", type=Path, help="private key (PEM) of --tls-cert")
    serve.add_argument(
        "--max-connections",
        type=int,
        default=BRIDGE.max_connections,
        help="bridge clients at once (default: %(default)s)",
    )
    serve.add_argument(
        "--max-connections-per-address",
        type=int,
        default=BRIDGE.max_connections_per_address,
        metavar="N",
        help="bridge clients at once from one address, its share of --max-connections"
        " (default: %(default)s; 0: no share; behind a proxy, every client has its address)",
    )
    serve.add_argument(
        "--header-timeout",
        type=float,
        default=HTTP.header_timeout,
        metavar="SECONDS",
        help="time a client has to send an HTTP request's head, or the bridge's"
        " handshake (default: %(default)g)",
    )
    serve.add_argument(
        "--robot",
        action="append",
        type=assignment,
        metavar="NAME=TASK",
        dest="robots",
        help="host a live robot running TASK at /robots/NAME (repeatable; default: "
        + " and ".join(f"{name}={task}" for name, task in registry.default_robots())
        + ")",
    )
    serve.add_argument("--no-robots", action="store_true", help="host no robot")
    serve.add_argument(
        "--lockstep",
        action="store_true",
        help="robots step only when /lab/step is called, as in trials (default: live)",
    )
    serve.add_argument(
        "--seed", type=int, default=0, help="the robots' first episode seed (default: 0)"
    )
    param_option(serve, "a task parameter for every robot (repeatable; default: the tasks' own)")
    serve.add_argument("--no-playground", action="store_true", help="host no playground graph")
    serve.add_argument(
        "--interface-ratio",
        type=float,
        default=LAB.interface_ratio,
        metavar="R",
        help="the share of the maze robot's page sessions shown the camera (interface A);"
        " the others see the tags and sensing without video (B) (default: %(default)s)",
    )
    drives = serve.add_argument_group(
        "what a drive of a live robot files (docs/live.md)", "Limits of 0 mean no limit."
    )
    drives.add_argument(
        "--max-drive-mb",
        type=int,
        default=DRIVES.max_record // MiB,
        metavar="N",
        help="MiB of a drive's record: there the drive ends, filed as it stands"
        " (default: %(default)s)",
    )
    drives.add_argument(
        "--min-drive-ticks",
        type=int,
        default=DRIVES.min_ticks,
        metavar="N",
        help="a client's drive shorter than this (or with no command) files nothing"
        " (default: %(default)s)",
    )
    drives.add_argument(
        "--drive-filings",
        type=int,
        default=DRIVES.filings_per_minute,
        metavar="N",
        help="drives a user, or else an address, may file a minute, over all the robots"
        " (default: %(default)s)",
    )
    group = serve.add_argument_group("the archive, the queue and its workers")
    group.add_argument(
        "--http-port",
        type=int,
        default=LAB.http_port,
        help="HTTP API port (default: %(default)s; 0: any free port)",
    )
    group.add_argument(
        "--public-url",
        metavar="URL",
        help="the address people and remote workers reach the HTTP port at, such as"
        " https://lab.example.org behind a proxy; the playground's repositories are"
        " recorded under URL/git/ (default: http://HOST:PORT as the lab listens)",
    )
    group.add_argument(
        "--http-connections-per-address",
        type=int,
        default=HTTP.max_connections_per_address,
        metavar="N",
        help="HTTP connections open at once from one address (default: %(default)s; 0: no limit)",
    )
    group.add_argument("--database", help="SQLAlchemy URL (default: sqlite:///DATA/index.sqlite)")
    group.add_argument(
        "--trusted-proxy",
        action="append",
        default=[],
        metavar="ADDR",
        dest="trusted_proxies",
        help="a reverse proxy (an address or network) whose X-Forwarded-For names the"
        " client; repeatable (default: none: the throttles count the socket's address)",
    )
    group.add_argument(
        "--blobs",
        help="blob store: a folder or an fsspec URL such as s3://bucket/prefix"
        " (default: DATA/blobs)",
    )
    group.add_argument(
        "--blobs-option",
        action="append",
        default=[],
        type=assignment,
        metavar="NAME=VALUE",
        help="an fsspec storage option for --blobs, e.g. endpoint_url=http://127.0.0.1:9000 "
        "(repeatable; S3 keys come from AWS_ACCESS_KEY_ID and AWS_SECRET_ACCESS_KEY)",
    )
    group.add_argument(
        "--workers",
        type=int,
        default=SERVICE.workers,
        help="trials run at once (default: %(default)s; 0: none)",
    )
    group.add_argument(
        "--worker-processes",
        type=int,
        default=SERVICE.worker_processes,
        metavar="N",
        help="trials run at once by worker processes of their own (labd worker against this"
        " lab), beside --workers in this process: a trial's lab side gets a core of its own"
        " (default: %(default)s)",
    )
    group.add_argument(
        "--videos",
        choices=MODES,
        default=SERVICE.videos,
        help="render replayed records' camera videos in the background while no trial runs or"
        " waits, or only when someone asks for one (default: %(default)s)",
    )
    group.add_argument(
        "--sandbox",
        choices=["docker", "bwrap"],
        help="isolation backend (default: docker if an engine answers, else bwrap)",
    )
    group.add_argument(
        "--max-data-trials",
        type=int,
        default=SERVICE.data_policy.max_trials,
        help="archived records one trial's [data] may pin (default: %(default)s)",
    )
    group.add_argument(
        "--max-data-mb",
        type=int,
        default=SERVICE.data_policy.max_bytes // MiB,
        help="MiB of records one trial's [data] may pin (default: %(default)s)",
    )
    group.add_argument(
        "--lease",
        type=float,
        default=SERVICE.queue.lease,
        help="seconds before a silent worker's trial is requeued (default: %(default)g)",
    )
    fetching.add_options(group)
    group.add_argument(
        "--resolve-timeout",
        type=float,
        default=fetching.DEFAULTS.resolve_timeout,
        metavar="S",
        help="seconds a submission may take to fetch its repository and resolve its ref,"
        " its submitter waiting (default: %(default)g; at most --fetch-timeout)",
    )
    group.add_argument(
        "--cache", type=Path, help="git mirrors and controller runtimes (default: DATA/cache)"
    )
    group.add_argument(
        "--canary",
        action="append",
        type=int,
        default=[],
        metavar="TRIAL",
        help="a reference trial each worker reruns when it starts and every --canary-every"
        " seconds; one that does not reproduce takes the worker out (repeatable; default: none)",
    )
    group.add_argument(
        "--canary-every",
        type=float,
        default=SERVICE.canary_every,
        help="seconds between a worker's canary reruns (default: %(default)g)",
    )
    group.add_argument(
        "--held-out-per-commit",
        type=int,
        default=SERVICE.held_out.per_commit,
        metavar="N",
        help="evaluations of a held-out suite version one user may have of one commit"
        " (reruns included; those the lab broke not counted; default: %(default)s)",
    )
    group.add_argument(
        "--held-out-per-day",
        type=int,
        default=SERVICE.held_out.per_day,
        metavar="N",
        help="evaluations of held-out suites one user may submit in 24 hours"
        " (default: %(default)s)",
    )
    group.add_argument(
        "--no-service", action="store_true", help="no HTTP API, no archive, no workers"
    )
    add_reservation_options(serve)


def _limit(value: float | None) -> str:
    return "no limit" if value is None else f"{value:g}"


def add_reservation_options(serve: Any) -> None:
    group = serve.add_argument_group(
        "accounts and reservations (docs/reservations.md)",
        "Limits of 0 mean no limit. Days are UTC days; weeks start on Monday.",
    )
    group.add_argument(
        "--reservations",
        action="store_true",
        help="only the holder of a reservation's key drives a live robot, in their slot"
        " (default: anyone connected may drive, one at a time)",
    )
    group.add_argument(
        "--no-watchers",
        action="store_true",
        help="with --reservations: a client needs a key even to watch (default: anyone may watch)",
    )
    group.add_argument(
        "--signup",
        action="store_true",
        help="people may make their own accounts on the sign-in page (default: only the"
        " operator, with labd users add)",
    )
    group.add_argument(
        "--max-slot",
        type=float,
        default=RULES.max_slot / 60,
        metavar="MIN",
        help="minutes a slot may last (default: %(default)g)",
    )
    group.add_argument(
        "--max-slots-per-day",
        type=int,
        default=RULES.max_slots_per_day,
        metavar="N",
        help=f"slots a person may have a day (default: {_limit(RULES.max_slots_per_day)})",
    )
    group.add_argument(
        "--max-minutes-per-day",
        type=float,
        default=RULES.max_minutes_per_day,
        metavar="MIN",
        help=f"minutes of slots a day (default: {_limit(RULES.max_minutes_per_day)})",
    )
    group.add_argument(
        "--max-slots-per-week",
        type=int,
        default=RULES.max_slots_per_week,
        metavar="N",
        help=f"slots a person may have a week (default: {_limit(RULES.max_slots_per_week)})",
    )
    group.add_argument(
        "--max-minutes-per-week",
        type=float,
        default=RULES.max_minutes_per_week,
        metavar="MIN",
        help=f"minutes of slots a week (default: {_limit(RULES.max_minutes_per_week)})",
    )
    group.add_argument(
        "--book-ahead",
        type=float,
        default=RULES.horizon / 86400,
        metavar="DAYS",
        help="how far ahead a slot may start (default: %(default)g days)",
    )


def config(args: argparse.Namespace) -> LabConfig:
    """The lab the options describe (``Refused`` if they make no sense together)."""
    robots = robot_configs(args)
    if not robots and args.no_playground:
        raise Refused("--no-robots with --no-playground leaves the bridge nothing to serve")
    if not 0.0 <= args.interface_ratio <= 1.0:
        raise Refused(f"--interface-ratio {args.interface_ratio:g}: give a share from 0 to 1")
    if args.reservations and args.no_service:
        raise Refused("--reservations needs the archive, where they are kept: drop --no-service")
    if args.reservations and args.authorizer:
        raise Refused(
            "--reservations makes the lab its own authorizer: drop --authorizer (or, to"
            " use an outside one, drop --reservations)"
        )
    if args.no_watchers and not args.reservations:
        raise Refused("--no-watchers goes with --reservations")
    if min(args.max_drive_mb, args.min_drive_ticks, args.drive_filings) < 0:
        raise Refused("--max-drive-mb, --min-drive-ticks and --drive-filings are 0 or more")
    if args.header_timeout <= 0:
        raise Refused(f"--header-timeout {args.header_timeout:g}: give a time over 0 seconds")
    if args.max_connections_per_address < 0 or args.http_connections_per_address < 0:
        raise Refused("the limits per address are a number of connections, or 0 for none")
    return LabConfig(
        data=args.data,
        bridge=bridge_config(args),
        robots=robots,
        playground=not args.no_playground,
        http_port=args.http_port,
        http=http_config(args),
        service=service_config(args),
        interface_ratio=args.interface_ratio,
        reservations=args.reservations,
        watchers=not args.no_watchers,
        drives=DriveLimits(
            max_record=args.max_drive_mb * MiB,
            min_ticks=args.min_drive_ticks,
            filings_per_minute=args.drive_filings,
        ),
        trusted_proxies=trusted_proxies(args),
    )


def trusted_proxies(args: argparse.Namespace) -> tuple[str, ...]:
    """The proxies ``--trusted-proxy`` names, each an address or a network."""
    for proxy in args.trusted_proxies:
        try:
            ipaddress.ip_network(proxy, strict=False)
        except ValueError:
            raise Refused(
                f"--trusted-proxy {proxy}: give the proxy's address (127.0.0.1) or network"
                " (10.0.0.0/8)"
            ) from None
    return tuple(args.trusted_proxies)


def rules(args: argparse.Namespace) -> Rules:
    """The booking rules the options set (0: no limit), within the lab's bounds."""
    if args.max_slot <= 0 or args.book_ahead <= 0:
        raise Refused("--max-slot and --book-ahead must be more than 0")
    if not args.max_slot <= MAX_SLOT / 60:
        raise Refused(f"--max-slot may be at most {MAX_SLOT / 60:g} minutes (a day)")
    if not args.book_ahead <= MAX_HORIZON / 86400:
        raise Refused(
            f"--book-ahead may be at most {MAX_HORIZON / 86400:g} days: bookings further"
            " ahead are refused"
        )

    def limit(value: float | None) -> float | None:
        if value is not None and value < 0:
            raise Refused("the limits per day and per week are 0 (no limit) or more")
        return value or None

    def count(value: int | None) -> int | None:
        found = limit(value)
        return None if found is None else int(found)

    return Rules(
        max_slot=args.max_slot * 60,
        max_slots_per_day=count(args.max_slots_per_day),
        max_minutes_per_day=limit(args.max_minutes_per_day),
        max_slots_per_week=count(args.max_slots_per_week),
        max_minutes_per_week=limit(args.max_minutes_per_week),
        horizon=args.book_ahead * 86400,
    )


def robot_configs(args: argparse.Namespace) -> tuple[RobotConfig, ...]:
    if args.no_robots:
        if args.robots:
            raise Refused("--robot and --no-robots contradict each other; give one")
        return ()
    pairs = list(args.robots) if args.robots else registry.default_robots()
    names = [name for name, _ in pairs]
    if len(set(names)) != len(names):
        raise Refused(f"two robots have the same name: {', '.join(names)}")
    params = tuple(args.param)
    robots = []
    for name, task in pairs:
        try:
            registry.validate(task, dict(params))
        except LabError as err:
            raise Refused(f"robot {name}: {err}") from None
        robots.append(RobotConfig(name, task, params, args.seed, live=not args.lockstep))
    return tuple(robots)


def service_config(args: argparse.Namespace) -> ServiceConfig | None:
    if args.no_service:
        return None
    if args.resolve_timeout <= 0:
        raise Refused(f"--resolve-timeout {args.resolve_timeout:g}: give more than 0 seconds")
    fetch = replace(fetching.policy(args, "labd serve"), resolve_timeout=args.resolve_timeout)
    if args.held_out_per_commit < 1 or args.held_out_per_day < 1:
        raise Refused("--held-out-per-commit and --held-out-per-day: give 1 or more")
    return ServiceConfig(
        data=args.data,
        database=args.database,
        blobs=args.blobs,
        blob_options=dict(args.blobs_option),
        cache=args.cache,
        workers=args.workers,
        sandbox=args.sandbox,
        queue=QueueConfig(lease=args.lease),
        heartbeat=max(0.5, args.lease / 3),
        fetch=fetch,
        run=RunOptions(fetch=fetch),
        data_policy=DataPolicy(args.max_data_trials, args.max_data_mb * MiB),
        canaries=tuple(args.canary),
        canary_every=args.canary_every,
        rules=rules(args),
        signup=args.signup,
        videos=args.videos,
        worker_processes=args.worker_processes,
        worker_options=tuple(fetching.argv(args)),
        public_url=public_url(args.public_url),
        held_out=HeldOutBudget(args.held_out_per_commit, args.held_out_per_day),
    )


def public_url(given: str | None) -> str | None:
    """``--public-url`` checked: an http(s) address with no path, query or fragment."""
    if given is None:
        return None
    parts = urlsplit(given)
    if parts.scheme not in ("http", "https") or not parts.netloc or parts.path.strip("/"):
        raise Refused(
            f"--public-url {given}: give the lab's address as people reach it, such as"
            " https://lab.example.org (http or https, no path)"
        )
    if parts.query or parts.fragment:
        raise Refused(f"--public-url {given}: give it without a query or fragment")
    return f"{parts.scheme}://{parts.netloc}"


def bridge_config(args: argparse.Namespace) -> BridgeConfig:
    if (args.tls_cert is None) != (args.tls_key is None):
        raise Refused("--tls-cert and --tls-key go together")
    if not args.key_recheck >= 0:
        raise Refused("--key-recheck is 0 (never) or more seconds")
    protected = tuple(args.protected) if args.protected else BRIDGE.protected_prefixes
    return BridgeConfig(
        host=args.host,
        port=args.bridge_port,
        protected_prefixes=protected,
        authorizer_url=args.authorizer,
        tls_cert=args.tls_cert,
        tls_key=args.tls_key,
        max_connections=args.max_connections,
        key_recheck=args.key_recheck or None,
        max_connections_per_address=args.max_connections_per_address,
        handshake_timeout=args.header_timeout,
    )


def http_config(args: argparse.Namespace) -> HttpConfig:
    return HttpConfig(
        header_timeout=args.header_timeout,
        max_connections_per_address=args.http_connections_per_address,
    )


def main(args: argparse.Namespace) -> int:
    return_freed_memory()
    raise_open_files_limit()
    sys.setswitchinterval(SWITCH_INTERVAL)
    try:
        lab_config = config(args)
        if getattr(args, "config", None) is not None:
            print(f"labd serve: settings from {args.config} (labd config show lists them)")
        asyncio.run(serve(lab_config))
    except Refused as err:
        return fail(args, str(err))
    except SchemaMismatch as err:
        where = f"--database {args.database}" if args.database else f"--data {args.data}"
        return fail(args, f"{err}: labd migrate {where}")
    except (ArchiveError, LabError, SandboxError, OSError) as err:
        return fail(args, str(err))
    return 0


async def serve(config: LabConfig) -> None:
    """Run the lab until SIGINT or SIGTERM; the data folder is its own meanwhile."""
    lock = DataLock.take(config.service.data) if config.service is not None else None
    if config.service is not None:  # one line per private path others may read
        for wide in privacy.wider(*privacy.lab_paths(config.service)):
            log.warning("%s", wide)
    try:
        await _serve(config, lock)
    finally:
        if lock is not None:
            lock.release()


async def _serve(config: LabConfig, lock: DataLock | None) -> None:
    lab = Lab(config)
    try:
        await lab.start()
    except BaseException:
        await lab.close()
        raise
    if lock is not None and lab.http is not None:
        lock.note(http=lab.http.url(), bridge=lab.bridge.url())
    bridge = lab.bridge
    print(f"labd {__version__}: rosbridge v2 on {bridge.url()}", flush=True)
    for name, robot in lab.robots.items():
        mode = "live" if robot.live else "lockstep"
        print(f"  robot {name} ({robot.sim.spec.name}, {mode}): {bridge.url(name)}", flush=True)
    if config.playground:
        print(f"  playground (no robot; clients meet here): {bridge.url('playground')}", flush=True)
    print(f"  {bridge.url()} serves the first of these.", flush=True)
    for plugin, why in registry.problems().items():
        print(f"  task plugin left out: {plugin}: {why}", flush=True)
    if config.reservations:
        watch = "anyone may watch" if config.watchers else "watching needs a key too"
        print(f"  live robots: only a reservation's key drives ({watch})", flush=True)
    if lab.http is not None and lab.service is not None:
        print(f"HTTP API on {lab.http.url()}/api (OpenAPI: {lab.http.url()}/openapi.json)")
        if lab.robots:
            print(f"  the robots' pages: {lab.http.url()}/robots", flush=True)
        archive = mask_url(lab.service.config.database_url)
        print(f"  archive: {archive}, blobs {mask_url(lab.service.store.url)}", flush=True)
        print(f"  workers: {len(lab.service.workers)}", flush=True)
        print(
            f"  records are signed with {lab.service.keyring.current}"
            f" (public keys: {lab.http.url()}/api/keys)",
            flush=True,
        )
        for names in lab.service.index.name_collisions():
            print(
                f"  warning: the users {' and '.join(names)} differ only in case (made by an"
                " older labd); they keep working, and no new name may join them",
                flush=True,
            )
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    try:
        await stop.wait()
    finally:
        await lab.close()


def raise_open_files_limit() -> None:
    """Raise the soft limit of open files to the hard one.

    Every client holds a descriptor; at the usual soft limit of 1,024, a thousand slow
    clients leave none for anyone else, and each refused ``accept()`` is logged (a
    slowloris attack did both). The hard limit is the operator's to set.
    """
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft == hard:
        return
    try:
        resource.setrlimit(resource.RLIMIT_NOFILE, (hard, hard))
    except (ValueError, OSError) as err:  # an unlimited hard limit the kernel caps lower
        log.warning("the open files limit stays at %d (raising it to %d: %s)", soft, hard, err)
        return
    log.info("open files limit raised from %d to %d", soft, hard)


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
    libc.mallopt(m_mmap_threshold, 128 * KiB)
