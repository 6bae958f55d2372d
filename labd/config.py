"""The lab's configuration: one object, built at start-up and passed down."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from repository.units import MiB
from repository.well_known import UX_EVENTS

DATA = Path("lab-data")  # where a lab keeps its archive, caches and runs, unless told


def database_url(data: Path, database: str | None = None) -> str:
    """The index's SQLAlchemy URL: ``database``, else the SQLite file in ``data``."""
    return database or f"sqlite:///{(data / 'index.sqlite').resolve()}"


@dataclass(frozen=True)
class BridgeConfig:
    """How the rosbridge server listens and what it allows each client."""

    host: str = "127.0.0.1"
    port: int = 9090
    # Names under these prefixes never cross the bridge (the rosjs paper's rule).
    protected_prefixes: tuple[str, ...] = ("/protected",)
    # Key authorization: an HTTP(S) URL answering {"seconds": N} for ?key=...
    authorizer_url: str | None = None
    auth_timeout: float = 10.0  # seconds a client has to authorize
    # A client is told (a status of level warning) this long before its key's time ends.
    expiry_warning: float = 60.0
    # Refused keys from one address, within the window, before the bridge refuses that
    # address's keys without asking the authorizer (guessing keys).
    auth_failures: int = 10
    auth_failure_window: float = 60.0
    # Seconds between asking the authorizer again about each connected client's key
    # (a revoked key disconnects its client within this); None or 0: never.
    key_recheck: float | None = 5.0
    tls_cert: Path | None = None
    tls_key: Path | None = None
    # Frames above max_message_size are refused with a status; the connection stays.
    # Frames above max_frame_size close the connection (1009), protecting memory.
    max_message_size: int = 16 * MiB
    max_frame_size: int = 64 * MiB
    max_connections: int = 200
    # Connections one address may hold (0: no share of its own), and as many again still
    # in their handshake: one address cannot take every slot. Unix sockets (a trial's
    # private bridge) have no address and no share.
    max_connections_per_address: int = 32
    handshake_timeout: float = 10.0  # seconds a client has to send its handshake
    max_queue_bytes: int = 32 * MiB  # per client, topic messages waiting to be sent
    default_queue_length: int = 100  # per subscription, when the client gives none
    ping_interval: float | None = 20.0
    ping_timeout: float | None = 20.0
    close_timeout: float = 5.0  # how long a closing peer may take before it is cut off
    service_timeout: float = 5.0  # call_service without a timeout field
    max_subscriptions: int = 1000  # per client, counting subscription ids
    max_publishers: int = 1000
    max_services: int = 200  # services a client provides, and actions likewise
    max_pending: int = 1000  # calls a client waits on, and goals likewise
    max_fragmented: int = 16  # messages a client may be sending in fragments at once
    fragment_timeout: float = 30.0
    log_rate: float = 20.0  # log lines per second per client before suppression
    log_burst: int = 50
    # Topics a client may publish on only so fast (messages per second, burst): a page's
    # user-experience events are many and small, and a flood of them must not crowd the
    # robot's data out of a record.
    rate_limits: tuple[tuple[str, float, int], ...] = ((UX_EVENTS, 50.0, 100),)


@dataclass(frozen=True)
class DriveLimits:
    """What a drive of a live robot may put in the archive (docs/live.md).

    A client's drive is filed under the name the lab knows it by, and only when it is a
    demonstration at all: it gave a command and lasted ``min_ticks``. Its user (a key's)
    or, for anyone else, its address may file ``filings_per_minute`` in any minute, over
    all the lab's robots. A record holds the robot's messages and the driver's commands
    and ``/ux/events``; past ``max_record`` bytes the driver's events are no longer
    recorded and the drive ends at the next tick, filed as it stands.
    """

    max_record: int = 64 * MiB
    min_ticks: int = 20  # one second at the live robots' 20 ticks a second
    filings_per_minute: int = 10
    # Characters of each text a client gives /lab/drive (its session, interface, user).
    max_text: int = 64


@dataclass(frozen=True)
class HttpConfig:
    """How the HTTP API and pages let clients in."""

    # Seconds a client has to send a request's head (its line and headers), from when it
    # connects or starts the next request on a kept connection (slowloris).
    header_timeout: float = 10.0
    # Connections one address may hold open at once (0: no limit).
    max_connections_per_address: int = 256
    keep_alive: float = 5.0  # seconds an idle kept connection stays open


@dataclass(frozen=True)
class RobotConfig:
    """A live robot that ``labd serve`` hosts at ``/robots/NAME``."""

    name: str  # e.g. icreate-1
    task: str  # a registered task, e.g. icreate-maze
    params: tuple[tuple[str, str], ...] = ()  # task parameters, as NAME=VALUE pairs
    seed: int = 0
    live: bool = True  # wall clock; False: lockstep, stepped by /lab/step


def assignment(text: str, *, last: bool = False) -> tuple[str, str]:
    """``NAME=VALUE`` as the pair ``(NAME, VALUE)``, both stripped: how a flag (``--param``,
    ``--robot``, ``--blobs-option``, ``--git-token``) or a form's line names a value. Split
    at the first ``=`` (``last``: at the last, where the name is a URL prefix that may hold
    one). ValueError, saying how to write it, when there is no ``=`` or no name."""
    name, sep, value = text.rpartition("=") if last else text.partition("=")
    if not sep or not name.strip():
        raise ValueError(f"{text!r}: write NAME=VALUE")
    return name.strip(), value.strip()
