"""``lab.toml``: what a controller repository tells the lab.

[controller]
command = ["python", "controller.py"]   # run from the repository root
task = "icreate-maze"                    # default task
tasks = ["dmc-cartpole-balance"]         # optional: the tasks it supports (benchmarks)
requirements = "requirements.txt"        # optional: installed in the build step
realtime = false                         # optional: true = wall clock, no lockstep
interfaces = "my_msgs"                   # optional: a ROS package's folder (or a list)

[data]                                   # optional: archived trials to learn from
trials = [12, 15]                        # by id, and/or a query:
query = { task = "icreate-maze", kind = "demonstration", outcome = "success", limit = 50 }

``tasks`` lists the tasks the controller supports (task names, each once), for benchmark
runs (issue 37), which are to refuse a benchmark with a task outside the list and, without
the list, to run every task. It is read and checked here; nothing uses it yet.

``interfaces`` names the folders of the repository's own interface packages, each laid
out as a ROS 2 package's: ``msg/*.msg``, ``srv/*.srv``, ``action/*.action``, the
folder's name being the package's (``my_msgs/msg/Debug.msg`` is ``my_msgs/msg/Debug``).
Their texts go to the lab side of the trial (``TrialHost.open``), which registers them
for that trial alone and refuses a malformed or conflicting one with its file and line.

A ``package.json`` at the root that names ``dependencies`` needs its
``package-lock.json`` beside it: the build step installs exactly what the lock says
(``npm ci``, no install scripts), and the lock's digest goes into the manifest.

``[data]`` is resolved when the trial is submitted (``scheduler.data``): the query
becomes a fixed list of records, pinned with their digests, so a rerun learns from the
same data.

Every file is read through ``scheduler.files.RepositoryFiles``: as regular files of
the repository, never through a symbolic link (which would be read on the lab's host).
"""

from __future__ import annotations

import json
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from typing import Any

from repository.digests import sha256_json
from repository.manifest import Controller
from repository.trial import MAX_ID, Kind, Outcome
from repository.units import MiB
from scheduler.errors import (
    ControllerConfigError,
    FileNotInRepository,
    NodePackagesError,
    RepositoryFileError,
)
from scheduler.files import RepositoryFiles, parts_of

FILE = "lab.toml"
PACKAGE = "package.json"
LOCK = "package-lock.json"
KEYS = ("command", "task", "tasks", "requirements", "realtime", "interfaces")
DATA_KEYS = ("trials", "query")
QUERY_KEYS = ("task", "kind", "outcome", "user", "limit")
INTERFACE_KINDS = ("msg", "srv", "action")
MAX_INTERFACE_FILES = 1000
MAX_INTERFACE_BYTES = 4 * MiB  # all of them together


@dataclass(frozen=True)
class DataQuery:
    """``[data].query``: finished, public trials with these fields, newest first."""

    task: str | None = None
    kind: Kind | None = None
    outcome: Outcome | None = None
    user: str | None = None  # the submitter (a demonstration's driver)
    limit: int | None = None  # at most this many (the newest); the lab caps it


@dataclass(frozen=True)
class DataSpec:
    """``[data]``: the archived trials a controller learns from, by id and/or a query."""

    trials: tuple[int, ...] = ()
    query: DataQuery | None = None


@dataclass(frozen=True)
class ControllerConfig:
    command: tuple[str, ...]
    task: str | None
    requirements: str | None
    realtime: bool
    text: str  # the file as written, for the trial record
    interfaces: tuple[str, ...] = ()  # the interface packages' folders lab.toml names
    # their .msg, .srv and .action files: path in the repository -> text
    interface_files: Mapping[str, str] = field(default_factory=dict)
    data: DataSpec | None = None  # [data], when lab.toml has it
    node_packages: bool = False  # package.json names dependencies: npm ci in the build step
    tasks: tuple[str, ...] = ()  # the tasks it supports; empty: lab.toml lists none

    @property
    def interfaces_sha256(self) -> str | None:
        """sha256 of the interface files (paths and texts), for the manifest; None without."""
        if not self.interfaces:
            return None
        # ASCII-escaped, as this digest always was: manifests that name it keep theirs
        return sha256_json(dict(self.interface_files), ascii_only=True)

    def in_manifest(
        self, *, requirements_sha256: str | None, node_packages_sha256: str | None
    ) -> Controller:
        """What a trial's manifest says of this controller, with the digests of what was
        installed for it."""
        return Controller(
            command=tuple(self.command),
            realtime=self.realtime,
            requirements=self.requirements,
            requirements_sha256=requirements_sha256,
            interfaces=tuple(self.interfaces),
            interfaces_sha256=self.interfaces_sha256,
            node_packages_sha256=node_packages_sha256,
        )


def load(code: Path | RepositoryFiles) -> ControllerConfig:
    """Read and check ``lab.toml`` at the root of the checkout ``code``.

    ``RepositoryFileError`` when lab.toml or the requirements file is a symbolic link
    (or passes through one), ``ControllerConfigError`` for anything else amiss.
    """
    files = code if isinstance(code, RepositoryFiles) else RepositoryFiles(code)
    if not files.is_file(FILE):
        raise ControllerConfigError(
            f"the repository has no {FILE} at its root; add one with a [controller] table "
            'naming the command, e.g. command = ["python", "controller.py"]'
        )
    try:
        text = files.read_text(FILE)
        data = tomllib.loads(text)
    except RepositoryFileError as err:
        raise ControllerConfigError(err.reason) from None
    except tomllib.TOMLDecodeError as err:
        raise ControllerConfigError(f"it is not valid TOML: {err}") from None
    table = data.get("controller")
    if not isinstance(table, dict):
        raise ControllerConfigError("it needs a [controller] table")
    unknown = sorted(set(table) - set(KEYS))
    if unknown:
        raise ControllerConfigError(
            f"[controller] has no key {unknown[0]!r}; the keys are {', '.join(KEYS)}"
        )
    folders, interface_files = _interfaces(files, table.get("interfaces"))
    return ControllerConfig(
        data=_data(data.get("data")),
        command=_command(table.get("command")),
        task=_optional_str(table, "task"),
        tasks=_tasks(table.get("tasks")),
        requirements=_requirements(files, table),
        realtime=_bool(table, "realtime"),
        text=text,
        interfaces=folders,
        interface_files=interface_files,
        node_packages=_node_packages(files),
    )


def _node_packages(files: RepositoryFiles) -> bool:
    """Whether the root's package.json names dependencies, which then need its lock."""
    if not files.is_file(PACKAGE):
        return False
    try:
        package = json.loads(files.read_text(PACKAGE))
    except RepositoryFileError as err:
        raise NodePackagesError(err.reason) from None
    except ValueError as err:
        raise NodePackagesError(f"{PACKAGE} is not valid JSON: {err}") from None
    dependencies = package.get("dependencies") if isinstance(package, dict) else None
    if dependencies is not None and not isinstance(dependencies, dict):
        raise NodePackagesError(f"{PACKAGE}: dependencies must be an object")
    if not dependencies:
        return False
    if not files.is_file(LOCK):
        raise NodePackagesError(
            f"{PACKAGE} names dependencies ({', '.join(sorted(dependencies)[:3])}) but the"
            f" repository has no {LOCK}; run npm install and commit {LOCK}"
        )
    return True


def _data(table: Any) -> DataSpec | None:
    """``[data]``, checked for its shape (what it matches is for ``scheduler.data``)."""
    if table is None:
        return None
    example = 'e.g. trials = [12, 15] or query = { task = "icreate-maze", kind = "demonstration" }'
    if not isinstance(table, dict):
        raise ControllerConfigError(f"[data] must be a table, {example}")
    unknown = sorted(set(table) - set(DATA_KEYS))
    if unknown:
        raise ControllerConfigError(
            f"[data] has no key {unknown[0]!r}; the keys are {', '.join(DATA_KEYS)}"
        )
    ids = table.get("trials", [])
    if not isinstance(ids, list) or not all(
        isinstance(i, int) and not isinstance(i, bool) and i > 0 for i in ids
    ):
        raise ControllerConfigError(f"[data] trials must be a list of trial ids, not {ids!r}")
    beyond = [i for i in ids if i > MAX_ID]
    if beyond:  # TOML reads any integer; the archive's ids are 32-bit (PostgreSQL's)
        raise ControllerConfigError(
            f"[data] trials: {beyond[0]} is no trial id (trial ids are 1 to {MAX_ID})"
        )
    query = table.get("query")
    if query is not None and not isinstance(query, dict):
        raise ControllerConfigError(f"[data] query must be an inline table, {example}")
    if not ids and query is None:
        raise ControllerConfigError(f"[data] names no trials and no query: {example}")
    return DataSpec(tuple(dict.fromkeys(ids)), None if query is None else _query(query))


def _query(table: dict[str, Any]) -> DataQuery:
    unknown = sorted(set(table) - set(QUERY_KEYS))
    if unknown:
        raise ControllerConfigError(
            f"[data] query has no key {unknown[0]!r}; the keys are {', '.join(QUERY_KEYS)}"
        )
    for key in ("task", "kind", "outcome", "user"):
        if key in table and not isinstance(table[key], str):
            raise ControllerConfigError(f"[data] query.{key} must be a string")
    if table.get("kind", Kind.TRIAL) not in set(Kind):
        raise ControllerConfigError(f"[data] query.kind is {' or '.join(Kind)}")
    if table.get("outcome", Outcome.SUCCESS) not in set(Outcome):
        raise ControllerConfigError(f"[data] query.outcome is one of {', '.join(Outcome)}")
    limit = table.get("limit")
    if limit is not None and (isinstance(limit, bool) or not isinstance(limit, int) or limit < 1):
        raise ControllerConfigError(f"[data] query.limit must be a positive integer, not {limit!r}")
    return DataQuery(
        task=table.get("task"),
        kind=Kind(table["kind"]) if "kind" in table else None,
        outcome=Outcome(table["outcome"]) if "outcome" in table else None,
        user=table.get("user"),
        limit=limit,
    )


def _command(value: Any) -> tuple[str, ...]:
    if value is None:
        raise ControllerConfigError('[controller] needs command, e.g. ["python", "controller.py"]')
    if isinstance(value, str):
        raise ControllerConfigError(
            f'command must be a list of strings, e.g. ["python", "controller.py"], not {value!r}'
        )
    if not isinstance(value, list) or not value:
        raise ControllerConfigError("command must be a non-empty list of strings")
    if not all(isinstance(part, str) and part for part in value):
        raise ControllerConfigError("every item of command must be a non-empty string")
    return tuple(value)


def _tasks(value: Any) -> tuple[str, ...]:
    """``tasks``: the task names the controller supports, each once (none: any task)."""
    if value is None:
        return ()
    if not isinstance(value, list) or not value:
        raise ControllerConfigError(
            f'tasks must be a non-empty list of task names, e.g. ["dmc-cartpole-balance"],'
            f" not {value!r}"
        )
    for name in value:
        if not isinstance(name, str) or not name:
            raise ControllerConfigError(f"every item of tasks must be a task's name, not {name!r}")
    again = sorted({name for name in value if value.count(name) > 1})
    if again:
        raise ControllerConfigError(f"tasks names {again[0]!r} more than once")
    return tuple(value)


def _optional_str(table: dict[str, Any], key: str) -> str | None:
    value = table.get(key)
    if value is not None and not isinstance(value, str):
        raise ControllerConfigError(f"{key} must be a string, not {value!r}")
    return value


def _bool(table: dict[str, Any], key: str) -> bool:
    value = table.get(key, False)
    if not isinstance(value, bool):
        raise ControllerConfigError(f"{key} must be true or false, not {value!r}")
    return value


def _requirements(files: RepositoryFiles, table: dict[str, Any]) -> str | None:
    """The requirements file's name, once it is known to be a regular UTF-8 file of
    the repository (so the install step may be handed it, and its hash taken)."""
    name = _optional_str(table, "requirements")
    if name is None:
        return None
    relative = PurePosixPath(name)
    if relative.is_absolute() or ".." in relative.parts:
        raise ControllerConfigError(f"requirements must be a path inside the repository: {name!r}")
    if not files.is_file(name):
        raise ControllerConfigError(f"requirements names {name!r}, which is not in the repository")
    files.read_text(name)  # refused here if it is not text, before anything is installed
    return name


def _interfaces(files: RepositoryFiles, value: Any) -> tuple[tuple[str, ...], dict[str, str]]:
    """The folders ``interfaces`` names, and the texts of their interface files.

    A link on the way to any of them is a ``RepositoryFileError`` naming it; the texts
    are checked by the lab side (``TrialHost.open``), which knows the types.
    """
    if value is None:
        return (), {}
    folders = [value] if isinstance(value, str) else value
    if not isinstance(folders, list) or not folders or not all(isinstance(f, str) for f in folders):
        raise ControllerConfigError(
            f'interfaces must name a folder, e.g. "my_msgs", or a list of folders, not {value!r}'
        )
    texts: dict[str, str] = {}
    size = 0
    for folder in folders:
        parts = parts_of(folder)
        if parts is None or parts == (".",):
            raise ControllerConfigError(
                f"interfaces must be folders inside the repository, not {folder!r}"
            )
        clean = "/".join(parts)
        try:
            files.listdir(clean)  # the folder itself, reached through no link
        except FileNotInRepository:
            raise ControllerConfigError(
                f"interfaces names {folder!r}, which is not a folder of the repository"
            ) from None
        found = 0
        for kind in INTERFACE_KINDS:
            try:
                names = files.listdir(f"{clean}/{kind}", f".{kind}")
            except FileNotInRepository:
                continue
            for name in names:
                if len(texts) >= MAX_INTERFACE_FILES:
                    raise ControllerConfigError(
                        f"interfaces hold more than {MAX_INTERFACE_FILES} files"
                    )
                texts[name] = files.read_text(name)
                size += len(texts[name])
                found += 1
        if size > MAX_INTERFACE_BYTES:
            raise ControllerConfigError(
                f"interfaces hold more than {MAX_INTERFACE_BYTES // MiB} MiB of text"
            )
        if not found:
            raise ControllerConfigError(
                f"interfaces names {folder!r}, which has no msg/*.msg, srv/*.srv or"
                " action/*.action file (it is laid out as a ROS package)"
            )
    return tuple("/".join(parts_of(f) or ()) for f in folders), texts
