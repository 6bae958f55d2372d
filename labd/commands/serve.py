"""``labd serve``: the lab. The bridge and its robots, the HTTP API, the archive, workers.

    labd serve [--host H] [--bridge-port P] [--http-port P] [--data DIR]
               [--robot NAME=TASK ... | --no-robots] [--lockstep] [--no-service] ...

Its settings are the table's (``labd.commands.settings``): their flags, and the
configuration objects the lab reads, built from them (``settings.build``); here are
only the checks of what the settings mean together, and what the lab works out from
them. A port in use, a certificate that does not load, an index of an older schema:
each stops it with one line saying what to change.
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
from typing import Any
from urllib.parse import urlsplit

from labd import __version__, oidc, privacy
from labd.commands import config as config_file
from labd.commands import fetching, settings
from labd.commands.common import fail
from labd.config import BridgeConfig, DriveLimits, HttpConfig, RobotConfig
from labd.datalock import DataLock
from labd.errors import LabError
from labd.lab import Lab, LabConfig
from labd.oidc import OidcConfig
from labd.service import ServiceConfig
from labd.sim import registry
from repository.errors import ArchiveError, SchemaMismatch
from repository.masking import mask_url
from repository.reservations import MAX_HORIZON, MAX_SLOT, Rules
from repository.units import KiB
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


class Refused(Exception):
    """A combination of options that cannot run; the message says what to change."""


def add_parser(commands: Any) -> None:
    """``labd serve`` and its settings (``labd.commands.settings``), in their groups."""
    serve = commands.add_parser(
        "serve",
        help="run the lab: the bridge and robots, the HTTP API, the archive and its workers",
    )
    settings.add(serve, settings.SERVE, grouped=True)


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
    check_proxies(args)
    return settings.build(
        LabConfig,
        args,
        bridge=bridge_config(args),
        robots=robots,
        http=settings.build(HttpConfig, args),
        service=service_config(args),
        drives=settings.build(DriveLimits, args),
    )


def check_proxies(args: argparse.Namespace) -> None:
    """Each ``--trusted-proxy`` is an address or a network."""
    for proxy in args.trusted_proxy:
        try:
            ipaddress.ip_network(proxy, strict=False)
        except ValueError:
            raise Refused(
                f"--trusted-proxy {proxy}: give the proxy's address (127.0.0.1) or network"
                " (10.0.0.0/8)"
            ) from None


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
    limits = (
        args.max_slots_per_day,
        args.max_minutes_per_day,
        args.max_slots_per_week,
        args.max_minutes_per_week,
    )
    if any(limit < 0 for limit in limits):
        raise Refused("the limits per day and per week are 0 (no limit) or more")
    return settings.build(Rules, args)


def robot_configs(args: argparse.Namespace) -> tuple[RobotConfig, ...]:
    if args.no_robots:
        if args.robot:
            raise Refused("--robot and --no-robots contradict each other; give one")
        return ()
    pairs = list(args.robot) if args.robot else registry.default_robots()
    names = [name for name, _ in pairs]
    if len(set(names)) != len(names):
        raise Refused(f"two robots have the same name: {', '.join(names)}")
    robots = []
    for name, task in pairs:
        try:
            registry.validate(task, dict(args.param))
        except LabError as err:
            raise Refused(f"robot {name}: {err}") from None
        robots.append(settings.build(RobotConfig, args, name=name, task=task))
    return tuple(robots)


def service_config(args: argparse.Namespace) -> ServiceConfig | None:
    if args.no_service:
        return None
    if args.resolve_timeout <= 0:
        raise Refused(f"--resolve-timeout {args.resolve_timeout:g}: give more than 0 seconds")
    if args.held_out_per_commit < 1 or args.held_out_per_day < 1:
        raise Refused("--held-out-per-commit and --held-out-per-day: give 1 or more")
    fetch = fetching.policy(args, "labd serve")
    queue = settings.build(QueueConfig, args)
    return settings.build(
        ServiceConfig,
        args,
        queue=queue,
        heartbeat=max(0.5, queue.lease / 3),  # a lease outlives two missed heartbeats
        fetch=fetch,
        run=RunOptions(fetch=fetch),
        data_policy=settings.build(DataPolicy, args),
        rules=rules(args),
        worker_options=tuple(fetching.argv(args)),
        public_url=public_url(args.public_url),
        held_out=settings.build(HeldOutBudget, args),
        oidc=oidc_config(args),
    )


def oidc_config(args: argparse.Namespace) -> OidcConfig:
    """The OpenID providers of the flags and of the configuration file's [oidc.NAME]."""
    document = config_file.read(args.config) if getattr(args, "config", None) else {}
    try:
        return oidc.configured(args, document)
    except oidc.OidcConfigError as err:
        raise Refused(str(err)) from None


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
    return settings.build(BridgeConfig, args)


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
        for provider in lab.service.config.oidc.providers:
            print(
                f"  sign-in with {provider.shown}: {lab.http.url()}/session/oidc/{provider.name}"
                f" (issuer {provider.issuer})",
                flush=True,
            )
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
