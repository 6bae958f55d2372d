"""``labd serve``'s settings, declared once: one row each in ``SETTINGS``.

A row (``Setting``) is a setting's name, the type and unit of its value, its help, its
group in ``labd serve --help``, and the fields of the lab's configuration objects it sets
(``into``). Everything else is derived from the rows:

- the flag ``--NAME-WITH-DASHES`` (``add``), in its group, its metavar its unit's;
- the key ``NAME`` of the configuration file's ``[serve]`` table and the variable
  ``LABD_NAME`` (``labd.commands.config`` reads both through the flag's own type);
- ``labd config show``'s lines, one a row;
- the configuration objects the lab reads (``build``): ``DriveLimits``, ``BridgeConfig``,
  ``Rules``... each field that a row sets, converted from the row's unit to the field's
  (``max_drive_mb`` 64 is ``DriveLimits.max_record`` 64 MiB in bytes);
- the list of settings in docs/operate.md (``markdown``; a test holds the two together).

A row's default is, unless it states one, the default of the first field it sets, in the
row's unit: a default is written once, where the lab's objects declare it (``lease`` is
``QueueConfig.lease``'s 30 s). The objects are named here, and imported only when a
command asks for their defaults, so that ``labd users`` shares ``data`` and ``database``
without loading the lab.

The names are the flags operators already use: the unit is in the name where it always
was (``max_drive_mb``, ``max_repo_mb``); for the others it is the row's ``unit``, shown
by ``--help`` (``--lease S``) and the docs.
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import Any, TypeVar

from labd.commands.common import assignment
from labd.config import DATA
from repository.units import MiB

T = TypeVar("T")


@dataclass(frozen=True)
class Unit:
    """What a number counts: its name in the docs, its metavar in ``--help``, and its size
    in the base unit of its kind (seconds for times, bytes for sizes)."""

    name: str
    metavar: str = "N"
    size: int = 1


COUNT = Unit("")
SECONDS = Unit("s", "S")
MINUTES = Unit("min", "MIN", 60)
DAYS = Unit("days", "DAYS", 86400)
BYTES = Unit("bytes")
MIB = Unit("MiB", "N", MiB)
SHARE = Unit("share", "R")  # from 0 to 1


@dataclass(frozen=True)
class Field:
    """A configuration object's field a setting sets, and the field's unit when it is
    not the setting's (``DriveLimits.max_record`` in ``BYTES``)."""

    owner: str  # a class in OWNERS
    name: str
    unit: Unit | None = None


def at(path: str, unit: Unit | None = None) -> Field:
    owner, _, name = path.partition(".")
    return Field(owner, name, unit)


# The configuration objects the settings set, and their modules: imported when asked for.
OWNERS = {
    "LabConfig": "labd.lab",
    "RobotConfig": "labd.config",
    "BridgeConfig": "labd.config",
    "HttpConfig": "labd.config",
    "DriveLimits": "labd.config",
    "ServiceConfig": "labd.service",
    "QueueConfig": "scheduler.queue",
    "FetchPolicy": "scheduler.fetch",
    "DataPolicy": "scheduler.data",
    "HeldOutBudget": "scheduler.evaluate",
    "Rules": "repository.reservations",
}


@dataclass(frozen=True)
class Group:
    """A section of ``labd serve --help`` and of the docs' list."""

    title: str
    description: str | None = None


LABD = Group("labd's own, before its command (labd --log-level INFO serve)")
BRIDGE = Group("the bridge and its robots (docs/protocol.md)")
DRIVES = Group("what a drive of a live robot files (docs/live.md)", "Limits of 0 mean no limit.")
ARCHIVE = Group("the archive, the queue and its workers (docs/service.md)")
FETCH = Group("what is fetched, and how (docs/service.md#submitting)")
ACCOUNTS = Group(
    "accounts and reservations (docs/reservations.md)",
    "Limits of 0 mean no limit. Days are UTC days; weeks start on Monday.",
)

_FROM_FIELD: Any = object()  # a row's default: its first field's


@dataclass(frozen=True)
class Setting:
    """One setting of ``labd serve``. ``help`` says what it does; ``{default}`` in it is
    where ``--help`` and the docs state the default (``note()``, when given, states it
    instead). A ``switch`` is on or off; a ``repeat`` setting is a list (``--flag`` once
    per item; its first use replaces the default). In the fields it sets, 0 is ``None``
    when ``zero_is_none`` ("no limit", "never"), and a switch is the field's opposite
    when ``opposite`` (``no_playground`` is ``LabConfig.playground``). A setting the
    command makes something of (``robot``: the robots) says what in ``worked_out``."""

    name: str
    help: str
    group: Group
    type: Callable[[str], Any] = str
    unit: Unit | None = None
    into: tuple[Field, ...] = ()
    default: Any = _FROM_FIELD
    metavar: str | None = None
    choices: Sequence[str] | Callable[[], Sequence[str]] | None = None
    switch: bool = False
    repeat: bool = False
    collect: Callable[[Iterable[Any]], Any] = tuple  # a repeat setting's items, as its field
    zero_is_none: bool = False
    opposite: bool = False
    note: Callable[[], str] | None = None
    worked_out: str = ""  # what the command makes of a setting that sets no field as it is

    @property
    def flag(self) -> str:
        return "--" + self.name.replace("_", "-")

    @property
    def variable(self) -> str:
        return "LABD_" + self.name.upper()


def _default_robots() -> str:
    from labd.sim import registry  # noqa: PLC0415 (the tasks: only for serve's help)

    return " and ".join(f"{name}={task}" for name, task in registry.default_robots())


def _video_modes() -> Sequence[str]:
    from labd.videos import MODES  # noqa: PLC0415 (imports the renderer's settings)

    return MODES


def _schemes(items: Iterable[str]) -> frozenset[str]:
    return frozenset(items)


SETTINGS: tuple[Setting, ...] = (
    # -- labd's own (every command takes it, and the configured ones from the file)
    Setting("log_level", "what the lab logs on stderr: INFO adds what it does, step by step"
            " (default: {default})", LABD, choices=("DEBUG", "INFO", "WARNING", "ERROR"),
            default="WARNING", worked_out="the log's level"),
    # -- the bridge and its robots
    Setting("host", "address to listen on (default: {default})", BRIDGE,
            metavar="ADDR", into=(at("BridgeConfig.host"),)),
    Setting("bridge_port", "rosbridge WebSocket port (default: {default}; 0: any free port)",
            BRIDGE, int, metavar="PORT", into=(at("BridgeConfig.port"),)),
    Setting("protected_prefix", "names under this prefix never cross the bridge (repeatable;"
            " default: {default})", BRIDGE, repeat=True, metavar="PREFIX",
            into=(at("BridgeConfig.protected_prefixes"),)),
    Setting("authorizer", 'require keys, checked at URL?key=KEY (answers {"seconds": N};'
            " default: {default})", BRIDGE, metavar="URL",
            into=(at("BridgeConfig.authorizer_url"),)),
    Setting("key_recheck", "seconds between asking the authorizer again about each connected"
            " client's key: a withdrawn key disconnects its client within this (default:"
            " {default}; 0: never)", BRIDGE, float, SECONDS, zero_is_none=True,
            into=(at("BridgeConfig.key_recheck"),)),
    Setting("tls_cert", "certificate (PEM): the robots are served at wss://, the pages and API"
            " at https:// (their cookies marked Secure) (default: none, plain ws:// and"
            " http://)", BRIDGE, Path, metavar="FILE", into=(at("BridgeConfig.tls_cert"),)),
    Setting("tls_key", "private key (PEM) of --tls-cert", BRIDGE, Path, metavar="FILE",
            into=(at("BridgeConfig.tls_key"),)),
    Setting("max_connections", "bridge clients at once (default: {default})", BRIDGE, int,
            COUNT, into=(at("BridgeConfig.max_connections"),)),
    Setting("max_connections_per_address", "bridge clients at once from one address, its"
            " share of --max-connections (default: {default}; 0: no share; behind a proxy,"
            " every client has its address)", BRIDGE, int, COUNT,
            into=(at("BridgeConfig.max_connections_per_address"),)),
    Setting("header_timeout", "time a client has to send an HTTP request's head, or the"
            " bridge's handshake (default: {default})", BRIDGE, float, SECONDS,
            into=(at("HttpConfig.header_timeout"), at("BridgeConfig.handshake_timeout"))),
    Setting("robot", "host a live robot running TASK at /robots/NAME (repeatable; default:"
            " {default})", BRIDGE, assignment, repeat=True, metavar="NAME=TASK", default=(),
            note=_default_robots, worked_out="`LabConfig.robots`"),
    Setting("no_robots", "host no robot", BRIDGE, switch=True, default=False,
            worked_out="`LabConfig.robots` (none)"),
    Setting("lockstep", "robots step only when /lab/step is called, as in trials (default:"
            " live)", BRIDGE, switch=True, opposite=True, into=(at("RobotConfig.live"),)),
    Setting("seed", "the robots' first episode seed (default: {default})", BRIDGE, int,
            metavar="N", into=(at("RobotConfig.seed"),)),
    Setting("param", "a task parameter for every robot (repeatable; default: the tasks' own)",
            BRIDGE, assignment, repeat=True, metavar="NAME=VALUE",
            into=(at("RobotConfig.params"),)),
    Setting("no_playground", "host no playground graph", BRIDGE, switch=True, opposite=True,
            into=(at("LabConfig.playground"),)),
    Setting("interface_ratio", "the share of the maze robot's page sessions shown the camera"
            " (interface A); the others see the tags and sensing without video (B) (default:"
            " {default})", BRIDGE, float, SHARE, into=(at("LabConfig.interface_ratio"),)),
    # -- what a drive of a live robot files
    Setting("max_drive_mb", "MiB of a drive's record: there the drive ends, filed as it stands"
            " (default: {default})", DRIVES, int, MIB,
            into=(at("DriveLimits.max_record", BYTES),)),
    Setting("min_drive_ticks", "a client's drive shorter than this (or with no command) files"
            " nothing (default: {default})", DRIVES, int, Unit("ticks"),
            into=(at("DriveLimits.min_ticks"),)),
    Setting("drive_filings", "drives a user, or else an address, may file a minute, over all"
            " the robots (default: {default})", DRIVES, int, Unit("per minute"),
            into=(at("DriveLimits.filings_per_minute"),)),
    # -- the archive, the queue and its workers
    Setting("data", "the lab's data folder: its archive, keys, caches and runs (default:"
            " {default})", ARCHIVE, Path, metavar="DIR", default=DATA,
            into=(at("LabConfig.data"), at("ServiceConfig.data"))),
    Setting("database", "SQLAlchemy URL (default: sqlite:///DATA/index.sqlite)", ARCHIVE,
            metavar="URL", default=None, into=(at("ServiceConfig.database"),)),
    Setting("blobs", "blob store: a folder or an fsspec URL such as s3://bucket/prefix"
            " (default: DATA/blobs)", ARCHIVE, metavar="URL", default=None,
            into=(at("ServiceConfig.blobs"),)),
    Setting("blobs_option", "an fsspec storage option for --blobs, e.g."
            " endpoint_url=http://127.0.0.1:9000 (repeatable; S3 keys come from"
            " AWS_ACCESS_KEY_ID and AWS_SECRET_ACCESS_KEY)", ARCHIVE, assignment, repeat=True,
            metavar="NAME=VALUE", default=(), collect=dict,
            into=(at("ServiceConfig.blob_options"),)),
    Setting("http_port", "HTTP API port (default: {default}; 0: any free port)", ARCHIVE, int,
            metavar="PORT", into=(at("LabConfig.http_port"),)),
    Setting("public_url", "the address people and remote workers reach the HTTP port at, such"
            " as https://lab.example.org behind a proxy; the playground's repositories are"
            " recorded under URL/git/ (default: http://HOST:PORT as the lab listens)", ARCHIVE,
            metavar="URL", default=None, worked_out="`ServiceConfig.public_url` (checked)"),
    Setting("http_connections_per_address", "HTTP connections open at once from one address"
            " (default: {default}; 0: no limit)", ARCHIVE, int, COUNT,
            into=(at("HttpConfig.max_connections_per_address"),)),
    Setting("trusted_proxy", "a reverse proxy (an address or network) whose X-Forwarded-For"
            " names the client; repeatable (default: none: the throttles count the socket's"
            " address)", ARCHIVE, repeat=True, metavar="ADDR",
            into=(at("LabConfig.trusted_proxies"),)),
    Setting("workers", "trials run at once (default: {default}; 0: none)", ARCHIVE, int, COUNT,
            into=(at("ServiceConfig.workers"),)),
    Setting("ray_address", "run trials, evaluations' episodes, reruns and replays on the Ray"
            " cluster at ADDRESS too (as ray.init takes it: HOST:PORT, or auto; needs"
            " labd[cluster]; docs/operate.md#a-cluster) (default: none)", ARCHIVE,
            metavar="ADDRESS", default=None, into=(at("ServiceConfig.ray_address"),)),
    Setting("worker_processes", "trials run at once by worker processes of their own (labd"
            " worker against this lab), beside --workers in this process: a trial's lab side"
            " gets a core of its own (default: {default})", ARCHIVE, int, COUNT,
            into=(at("ServiceConfig.worker_processes"),)),
    Setting("videos", "render replayed records' camera videos in the background while no trial"
            " runs or waits, or only when someone asks for one (default: {default})", ARCHIVE,
            choices=_video_modes, into=(at("ServiceConfig.videos"),)),
    Setting("sandbox", "isolation backend (default: docker if an engine answers, else bwrap)",
            ARCHIVE, choices=("docker", "bwrap"), into=(at("ServiceConfig.sandbox"),)),
    Setting("max_data_trials", "archived records one trial's [data] may pin (default:"
            " {default})", ARCHIVE, int, COUNT, into=(at("DataPolicy.max_trials"),)),
    Setting("max_data_mb", "MiB of records one trial's [data] may pin (default: {default})",
            ARCHIVE, int, MIB, into=(at("DataPolicy.max_bytes", BYTES),)),
    Setting("lease", "seconds before a silent worker's trial is requeued; its worker renews it"
            " every third of it (default: {default})", ARCHIVE, float, SECONDS,
            into=(at("QueueConfig.lease"),)),
    Setting("resolve_timeout", "seconds a submission may take to fetch its repository and"
            " resolve its ref, its submitter waiting (default: {default}; at most"
            " --fetch-timeout)", ARCHIVE, float, SECONDS,
            into=(at("FetchPolicy.resolve_timeout"),)),
    Setting("cache", "git mirrors and controller runtimes (default: DATA/cache)", ARCHIVE, Path,
            metavar="DIR", into=(at("ServiceConfig.cache"),)),
    Setting("canary", "a reference trial each worker reruns when it starts and every"
            " --canary-every seconds; one that does not reproduce takes the worker out"
            " (repeatable; default: none)", ARCHIVE, int, repeat=True, metavar="TRIAL",
            into=(at("ServiceConfig.canaries"),)),
    Setting("canary_every", "seconds between a worker's canary reruns (default: {default})",
            ARCHIVE, float, SECONDS, into=(at("ServiceConfig.canary_every"),)),
    Setting("held_out_per_commit", "evaluations of a held-out suite version one user may have"
            " of one commit (reruns included; those the lab broke not counted; default:"
            " {default})", ARCHIVE, int, COUNT, into=(at("HeldOutBudget.per_commit"),)),
    Setting("held_out_per_day", "evaluations of held-out suites one user may submit in 24 hours"
            " (default: {default})", ARCHIVE, int, COUNT, into=(at("HeldOutBudget.per_day"),)),
    Setting("no_service", "no HTTP API, no archive, no workers", ARCHIVE, switch=True,
            default=False, worked_out="`LabConfig.service` (none)"),
    # -- what is fetched, and how (labd worker takes these too)
    Setting("allow_scheme", "repository URL schemes accepted (repeatable; default: {default};"
            " add http for plain HTTP)", FETCH, repeat=True, metavar="SCHEME", collect=_schemes,
            into=(at("FetchPolicy.schemes"),)),
    Setting("allow_local_repos", "accept local paths and file:// URLs as repositories: whoever"
            " may submit then reaches this machine's folders (default: refused; the lab's own"
            " are always refused)", FETCH, switch=True, default=False,
            worked_out="`FetchPolicy.schemes` (file)"),
    Setting("allow_private_hosts", "fetch from hosts at loopback, link-local and private"
            " addresses too: whoever may submit then reaches this machine's ports and its"
            " network (default: refused; the lab's own repositories are always fetched)",
            FETCH, switch=True, into=(at("FetchPolicy.private_hosts"),)),
    Setting("max_repo_mb", "largest repository fetched, in MiB (default: {default})", FETCH,
            int, MIB, into=(at("FetchPolicy.max_bytes", BYTES),)),
    Setting("max_checkout_mb", "largest commit checked out (its files added up, as written to"
            " disk), in MiB (default: {default})", FETCH, int, MIB,
            into=(at("FetchPolicy.max_checkout_bytes", BYTES),)),
    Setting("fetch_timeout", "seconds a fetch may take (default: {default})", FETCH, float,
            SECONDS, into=(at("FetchPolicy.timeout"),)),
    Setting("submodule_allow", "submodules whose URL starts with this may be followed"
            " (repeatable; default: {default})", FETCH, repeat=True, metavar="URL_PREFIX",
            into=(at("FetchPolicy.submodules"),)),
    Setting("git_token", "for private https repositories under URL_PREFIX: a token, read from"
            " FILE (repeatable; default: none); git alone sees it, never a controller", FETCH,
            repeat=True, metavar="URL_PREFIX=FILE", default=(),
            worked_out="`FetchPolicy.credentials`"),
    Setting("git_ssh_key", "for private ssh repositories under URL_PREFIX: a deploy key"
            " (repeatable; default: none)", FETCH, repeat=True, metavar="URL_PREFIX=KEYFILE",
            default=(), worked_out="`FetchPolicy.credentials`"),
    # -- accounts and reservations
    Setting("reservations", "only the holder of a reservation's key drives a live robot, in"
            " their slot (default: anyone connected may drive, one at a time)", ACCOUNTS,
            switch=True, into=(at("LabConfig.reservations"),)),
    Setting("no_watchers", "with --reservations: a client needs a key even to watch (default:"
            " anyone may watch)", ACCOUNTS, switch=True, opposite=True,
            into=(at("LabConfig.watchers"),)),
    Setting("signup", "people may make their own accounts on the sign-in page (default: only"
            " the operator, with labd users add)", ACCOUNTS, switch=True,
            into=(at("ServiceConfig.signup"),)),
    Setting("oidc_issuer", "people sign in through this OpenID Connect provider (its"
            " https:// issuer; several: [oidc.NAME] tables in the configuration file; default:"
            " none)", ACCOUNTS, metavar="URL", default=None, worked_out="`OidcConfig.providers`"),
    Setting("oidc_client_id", "the lab's client id at --oidc-issuer", ACCOUNTS, metavar="ID",
            default=None, worked_out="`OidcConfig.providers`"),
    Setting("oidc_client_secret", "the lab's client secret at --oidc-issuer (default: none, a"
            " public client)", ACCOUNTS, metavar="SECRET", default=None,
            worked_out="`OidcConfig.providers`"),
    Setting("oidc_name", "what the sign-in page calls --oidc-issuer: Sign in with NAME"
            " (default: its host)", ACCOUNTS, metavar="NAME", default=None,
            worked_out="`OidcConfig.providers`"),
    Setting("oidc_allow_domain", "only people whose provider vouches for an e-mail address in"
            " this domain make an account by signing in (repeatable; default: anyone)",
            ACCOUNTS, repeat=True, metavar="DOMAIN", default=(),
            worked_out="`OidcConfig.domains`"),
    Setting("oidc_invite", "and this e-mail address, whatever its domain (repeatable;"
            " default: none)", ACCOUNTS, repeat=True, metavar="EMAIL", default=(),
            worked_out="`OidcConfig.invited`"),
    Setting("max_slot", "minutes a slot may last (default: {default})", ACCOUNTS, float,
            MINUTES, into=(at("Rules.max_slot", SECONDS),)),
    Setting("max_slots_per_day", "slots a person may have a day (default: {default})",
            ACCOUNTS, int, COUNT, zero_is_none=True, into=(at("Rules.max_slots_per_day"),)),
    Setting("max_minutes_per_day", "minutes of slots a day (default: {default})", ACCOUNTS,
            float, MINUTES, zero_is_none=True, into=(at("Rules.max_minutes_per_day"),)),
    Setting("max_slots_per_week", "slots a person may have a week (default: {default})",
            ACCOUNTS, int, COUNT, zero_is_none=True, into=(at("Rules.max_slots_per_week"),)),
    Setting("max_minutes_per_week", "minutes of slots a week (default: {default})", ACCOUNTS,
            float, MINUTES, zero_is_none=True, into=(at("Rules.max_minutes_per_week"),)),
    Setting("book_ahead", "how far ahead a slot may start (default: {default} days)", ACCOUNTS,
            float, DAYS, into=(at("Rules.horizon", SECONDS),)),
)  # fmt: skip
BY_NAME = {row.name: row for row in SETTINGS}
SERVE = tuple(row for row in SETTINGS if row.group is not LABD)  # labd serve's flags


def get(name: str) -> Setting:
    return BY_NAME[name]


def group(which: Group) -> list[Setting]:
    return [row for row in SETTINGS if row.group is which]


# -- defaults -----------------------------------------------------------------------------


def owner(name: str) -> type:
    """The configuration class ``name`` (``OWNERS``), imported now."""
    found: type = getattr(importlib.import_module(OWNERS[name]), name)
    return found


def field_default(target: Field) -> Any:
    """The default of a configuration object's field."""
    for each in dataclasses.fields(owner(target.owner)):
        if each.name == target.name:
            if each.default is not dataclasses.MISSING:
                return each.default
            if each.default_factory is not dataclasses.MISSING:
                return each.default_factory()
            raise LookupError(f"{target.owner}.{target.name} has no default")
    raise LookupError(f"{target.owner} has no field {target.name}")


def default(row: Setting) -> Any:
    """The row's default, in its unit: its own, or its first field's. A repeat setting's
    is a new list each time."""
    found = _from_its_field(row.name) if row.default is _FROM_FIELD else row.default
    return list(found) if row.repeat else found


@cache
def _from_its_field(name: str) -> Any:
    row = BY_NAME[name]
    return from_field(row, row.into[0], field_default(row.into[0]))


def from_field(row: Setting, target: Field, value: Any) -> Any:
    """A field's value as the setting states it (``to_field``'s inverse)."""
    if row.switch:
        return not value if row.opposite else bool(value)
    if row.repeat:
        items = value.items() if isinstance(value, Mapping) else value
        return sorted(items) if isinstance(value, frozenset) else list(items)
    if value is None:
        return 0 if row.zero_is_none else None
    scale = _scale(row, target)
    if scale != 1:
        value = value / scale
    return row.type(value) if row.type in (int, float) else value


def to_field(row: Setting, target: Field, value: Any) -> Any:
    """The setting's value as the field holds it: in the field's unit, 0 as ``None`` where
    0 means no limit, a list as the field's collection, a switch as its opposite."""
    if row.switch:
        return not value if row.opposite else bool(value)
    if row.repeat:
        return row.collect(value)
    if value is None or (row.zero_is_none and value == 0):
        return None
    scale = _scale(row, target)
    return value * scale if scale != 1 else value


def _scale(row: Setting, target: Field) -> int:
    if target.unit is None or row.unit is None:
        return 1
    return row.unit.size // target.unit.size


# -- the configuration objects -------------------------------------------------------------


def values(cls: type, args: argparse.Namespace) -> dict[str, Any]:
    """The fields of ``cls`` that the settings in ``args`` set, each in the field's unit."""
    found: dict[str, Any] = {}
    for row in SETTINGS:
        if not hasattr(args, row.name):  # a setting this command does not take
            continue
        for target in row.into:
            if target.owner == cls.__name__:
                found[target.name] = to_field(row, target, getattr(args, row.name))
    return found


def build(cls: type[T], args: argparse.Namespace, **worked_out: Any) -> T:
    """``cls`` made of the settings' values in ``args`` and the fields ``worked_out`` from
    them by the command (a field set both ways is a TypeError: no setting is mapped twice)."""
    return cls(**values(cls, args), **worked_out)


# -- the flags ------------------------------------------------------------------------------


class Repeat(argparse._AppendAction):
    """A repeatable flag: its first use replaces the default, later ones add to it
    (argparse's ``append`` adds the first to the default too)."""

    def __call__(
        self,
        parser: argparse.ArgumentParser,
        namespace: argparse.Namespace,
        values: Any,
        option_string: str | None = None,
    ) -> None:
        items: list[Any] | None = getattr(namespace, self.dest, None)
        kept = [] if items is None or items is self.default else list(items)
        setattr(namespace, self.dest, [*kept, values])


def shown(row: Setting, value: Any) -> str:
    """A default as ``--help`` and the docs state it."""
    if row.note is not None:
        return row.note()
    if value is None or value == []:
        return "none"
    if isinstance(value, list):
        return " ".join(shown(row, item) for item in value)
    if isinstance(value, tuple):  # a NAME=VALUE pair
        return "=".join(value)
    if isinstance(value, float):
        return f"{value:g}"
    return str(value)


def help_text(row: Setting, value: Any) -> str:
    return row.help.replace("{default}", shown(row, value))


def add(parser: Any, rows: Iterable[Setting], *, grouped: bool = False) -> None:
    """The rows' flags on ``parser`` (an argparse parser or group); with ``grouped``, each
    in its row's group, the groups in the table's order."""
    groups: dict[Group, Any] = {}
    for row in rows:
        where = parser
        if grouped:
            if row.group not in groups:
                groups[row.group] = parser.add_argument_group(
                    row.group.title, row.group.description
                )
            where = groups[row.group]
        add_one(where, row)


def add_one(parser: Any, row: Setting) -> None:
    value = default(row)
    options: dict[str, Any] = {
        "dest": row.name,
        "default": value,
        "help": help_text(row, value).replace("%", "%%"),
    }
    if row.switch:
        parser.add_argument(row.flag, action="store_true", **options)
        return
    choices = row.choices() if callable(row.choices) else row.choices
    metavar = row.metavar or (row.unit.metavar if row.unit is not None else None)
    if metavar is None and choices is None:
        metavar = row.name.upper()
    options.update(
        type=None if row.type is str else row.type,
        choices=choices,
        metavar=metavar,
        action=Repeat if row.repeat else "store",
    )
    parser.add_argument(row.flag, **options)


def argv(args: argparse.Namespace, rows: Iterable[Setting]) -> list[str]:
    """The rows' values in ``args`` as a command line (for another labd command: the worker
    processes ``labd serve`` starts). A switch that is off, and an empty list, say nothing."""
    out: list[str] = []
    for row in rows:
        value = getattr(args, row.name)
        if row.switch:
            out += [row.flag] if value else []
            continue
        for item in value if row.repeat else [value]:
            if item is not None:
                out += [row.flag, _text(item)]
    return out


def _text(value: Any) -> str:
    if isinstance(value, tuple):
        return "=".join(value)
    if isinstance(value, float):
        return f"{value:g}"
    return str(value)


# -- the docs -------------------------------------------------------------------------------


def markdown() -> str:
    """The list of settings in docs/operate.md: per group, each setting's key, unit, what
    it does (with its default) and the field it sets."""
    lines: list[str] = []
    for which in dict.fromkeys(row.group for row in SETTINGS):
        lines += ["", f"*{which.title}*" + (f". {which.description}" if which.description else "")]
        lines += ["", "| setting | unit | what it does | sets |", "|---|---|---|---|"]
        for row in group(which):
            unit = row.unit.name if row.unit is not None else ""
            what = help_text(row, default(row)).replace("|", "\\|")
            sets = ", ".join(
                f"`{t.owner}.{t.name}`" + (f" ({t.unit.name})" if t.unit else "") for t in row.into
            )
            sets = sets or f"{row.worked_out}, by the command"
            lines.append(f"| `{row.name}` | {unit} | {what} | {sets} |")
    return "\n".join(lines[1:]) + "\n"
