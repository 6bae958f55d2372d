"""What ran: a record's manifest, one typed value, written and read side by side.

A manifest says everything that decided what a record holds: the task and its version,
its parameters and seed, the simulator's versions and the compiled model's digest, and
what drove the robot (a controller's code, or a person at a live robot). Its digest (the
sha256 of its canonical JSON, ``repository.digests``) names the experiment, the record
holds it, and the lab signs it. So it is written one way, byte for byte as records filed
long ago hold it, and read back from every one of them: each part's ``to_json`` and
``from_json`` sit side by side here, as mcap's ``records.py`` keeps each record's, and
``tests/data/manifests`` holds one of every kind ever filed to both.

Two kinds, two constructors (their keys in the order they are written; ``[...]`` only
when there is something to say, so that manifests written before keep their digests):

``Manifest.trial`` (``scheduler.runner`` through the lab, ``labd.trial``)::

    schema, repository, commit, tree, git_tree, subdir, dirty,
    task {name, version}, parameters, seed,
    controller {command, realtime, requirements, requirements_sha256,
                [interfaces, interfaces_sha256], [node_packages_sha256]},
    runtime, versions {labd, mujoco, dm_control, python}, model_sha256,
    [data [{trial, data_digest, mcap}]], [blind: true]

``Manifest.drive`` (a live robot's drive, ``labd.live``)::

    schema, kind: "demonstration", robot, task {name, version}, parameters, seed,
    live: true, controller {realtime: true},
    driver {user, interface, session, [claimed_user]}, versions, model_sha256

Reading is strict: a key missing, of another type, or not one the lab writes is a
``ManifestError`` naming it (a missing seed is an error, never 0), since a manifest this
code could not write back as it was would not keep its digest.
"""

from __future__ import annotations

import functools
import platform
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from importlib import metadata
from typing import Any

from repository.digests import manifest_digest
from repository.errors import ManifestError
from repository.trial import Kind, PinnedRecord, Value

SCHEMA = "labd.trial/1"


class _Reader:
    """One JSON object of a manifest being read: each key taken once and checked, and
    any left over named as an error (``done``)."""

    def __init__(self, value: Any, where: str) -> None:
        if not isinstance(value, dict):
            raise ManifestError(where, f"must be an object, not {_shown(value)}")
        self.value: dict[str, Any] = value
        self.where = where
        self._taken: set[str] = set()

    def has(self, key: str) -> bool:
        return key in self.value

    def raw(self, key: str) -> Any:
        if key not in self.value:
            raise ManifestError(f"{self.where}.{key}", "missing")
        self._taken.add(key)
        return self.value[key]

    def text(self, key: str) -> str:
        value = self.raw(key)
        if not isinstance(value, str):
            raise ManifestError(f"{self.where}.{key}", f"must be a string, not {_shown(value)}")
        return value

    def text_or_none(self, key: str) -> str | None:
        return None if self.raw(key) is None else self.text(key)

    def integer(self, key: str) -> int:
        value = self.raw(key)
        if isinstance(value, bool) or not isinstance(value, int):
            raise ManifestError(f"{self.where}.{key}", f"must be an integer, not {_shown(value)}")
        return value

    def flag(self, key: str) -> bool:
        value = self.raw(key)
        if not isinstance(value, bool):
            raise ManifestError(
                f"{self.where}.{key}", f"must be true or false, not {_shown(value)}"
            )
        return value

    def true(self, key: str) -> None:
        """A key that is written only as ``true``."""
        if self.raw(key) is not True:
            raise ManifestError(f"{self.where}.{key}", "is written only as true")

    def texts(self, key: str) -> tuple[str, ...]:
        value = self.raw(key)
        if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
            raise ManifestError(f"{self.where}.{key}", f"must be a list of strings, not {value!r}")
        return tuple(value)

    def object(self, key: str) -> _Reader:
        return _Reader(self.raw(key), f"{self.where}.{key}")

    def done(self) -> None:
        unknown = sorted(set(self.value) - self._taken)
        if unknown:
            raise ManifestError(self.where, f"{unknown[0]!r} is not a key the lab writes here")


def _shown(value: Any) -> str:
    return "null" if value is None else repr(value)


@dataclass(frozen=True)
class Code:
    """The code a trial ran, and how to name it (``scheduler.source.checkout``)."""

    repository: str  # the URL, or the folder's absolute path
    commit: str | None  # None for a plain folder or one with uncommitted changes
    tree: str  # "sha256:..." over the files run (paths, executable bits, contents)
    git_tree: str | None  # git's tree hash of the commit's folder
    subdir: str  # the folder within the repository ("" for its root)
    dirty: bool  # a local folder that differs from its commit

    def to_json(self) -> dict[str, Any]:  # written at the manifest's top level
        return {
            "repository": self.repository,
            "commit": self.commit,
            "tree": self.tree,
            "git_tree": self.git_tree,
            "subdir": self.subdir,
            "dirty": self.dirty,
        }

    @classmethod
    def read(cls, top: _Reader) -> Code:
        return cls(
            repository=top.text("repository"),
            commit=top.text_or_none("commit"),
            tree=top.text("tree"),
            git_tree=top.text_or_none("git_tree"),
            subdir=top.text("subdir"),
            dirty=top.flag("dirty"),
        )


@dataclass(frozen=True)
class Team:
    """One side of a match's leg: its code, and its controller as ``lab.toml`` declared it."""

    code: Code
    controller: Controller

    def to_json(self) -> dict[str, Any]:
        return {**self.code.to_json(), "controller": self.controller.to_json()}

    @classmethod
    def read(cls, team: _Reader) -> Team:
        found = cls(Code.read(team), Controller.read(team.object("controller")))
        team.done()
        return found


@dataclass(frozen=True)
class TaskVersion:
    """The task, and the version of it that ran."""

    name: str
    version: str

    def to_json(self) -> dict[str, Any]:
        return {"name": self.name, "version": self.version}

    @classmethod
    def read(cls, task: _Reader) -> TaskVersion:
        found = cls(name=task.text("name"), version=task.text("version"))
        task.done()
        return found


@dataclass(frozen=True)
class Controller:
    """A trial's controller: what ``lab.toml`` declared, and the digests of what was
    installed for it (requirements, interface files, node packages)."""

    command: tuple[str, ...]
    realtime: bool
    requirements: str | None  # the requirements file lab.toml names
    requirements_sha256: str | None
    interfaces: tuple[str, ...] = ()  # the repository's own interface packages
    interfaces_sha256: str | None = None
    node_packages_sha256: str | None = None  # of package-lock.json

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "command": list(self.command),
            "realtime": self.realtime,
            "requirements": self.requirements,
            "requirements_sha256": self.requirements_sha256,
        }
        if self.interfaces:  # only then, so manifests without keep their digests
            out["interfaces"] = list(self.interfaces)
            out["interfaces_sha256"] = self.interfaces_sha256
        if self.node_packages_sha256 is not None:  # likewise
            out["node_packages_sha256"] = self.node_packages_sha256
        return out

    @classmethod
    def read(cls, controller: _Reader) -> Controller:
        interfaces: tuple[str, ...] = ()
        interfaces_sha256 = None
        if controller.has("interfaces") or controller.has("interfaces_sha256"):
            interfaces = controller.texts("interfaces")
            interfaces_sha256 = controller.text("interfaces_sha256")
            if not interfaces:
                raise ManifestError(f"{controller.where}.interfaces", "is written only with some")
        found = cls(
            command=controller.texts("command"),
            realtime=controller.flag("realtime"),
            requirements=controller.text_or_none("requirements"),
            requirements_sha256=controller.text_or_none("requirements_sha256"),
            interfaces=interfaces,
            interfaces_sha256=interfaces_sha256,
            node_packages_sha256=controller.text("node_packages_sha256")
            if controller.has("node_packages_sha256")
            else None,
        )
        controller.done()
        return found


@dataclass(frozen=True)
class Versions:
    """The versions of the lab and its simulator that ran: a replay needs the same
    mujoco and dm_control."""

    labd: str
    mujoco: str
    dm_control: str
    python: str

    def to_json(self) -> dict[str, Any]:
        return {
            "labd": self.labd,
            "mujoco": self.mujoco,
            "dm_control": self.dm_control,
            "python": self.python,
        }

    @classmethod
    def read(cls, versions: _Reader) -> Versions:
        found = cls(
            labd=versions.text("labd"),
            mujoco=versions.text("mujoco"),
            dm_control=versions.text("dm_control"),
            python=versions.text("python"),
        )
        versions.done()
        return found

    @classmethod
    def here(cls) -> Versions:
        """The versions this process runs (looked up once: 10 ms a trial otherwise)."""
        return _here()


@functools.cache
def _here() -> Versions:
    return Versions(
        labd=_version("labd"),
        mujoco=_version("mujoco"),
        dm_control=_version("dm-control"),
        python=platform.python_version(),
    )


def _version(package: str) -> str:
    try:
        return metadata.version(package)
    except metadata.PackageNotFoundError:
        return "unknown"


@dataclass(frozen=True)
class Pinned:
    """An archived record a trial learnt from, as its manifest names it."""

    trial: int
    data_digest: str
    mcap: str

    def to_json(self) -> dict[str, Any]:
        return {"trial": self.trial, "data_digest": self.data_digest, "mcap": self.mcap}

    @classmethod
    def read(cls, entry: _Reader) -> Pinned:
        found = cls(
            trial=entry.integer("trial"),
            data_digest=entry.text("data_digest"),
            mcap=entry.text("mcap"),
        )
        entry.done()
        return found

    @classmethod
    def of(cls, record: PinnedRecord) -> Pinned:
        return cls.read(_Reader(record.manifest_entry(), "data"))


@dataclass(frozen=True)
class Driver:
    """Who drove a live robot: the user the lab knows the client as, the interface and
    session it named, and the user it typed when that is another (unchecked)."""

    user: str
    interface: str
    session: str
    claimed_user: str = ""

    def to_json(self) -> dict[str, Any]:
        out = {"user": self.user, "interface": self.interface, "session": self.session}
        if self.claimed_user:
            out["claimed_user"] = self.claimed_user
        return out

    @classmethod
    def read(cls, driver: _Reader) -> Driver:
        claimed = driver.text("claimed_user") if driver.has("claimed_user") else ""
        if driver.has("claimed_user") and not claimed:
            raise ManifestError(f"{driver.where}.claimed_user", "is written only when given")
        found = cls(
            user=driver.text("user"),
            interface=driver.text("interface"),
            session=driver.text("session"),
            claimed_user=claimed,
        )
        driver.done()
        return found


@dataclass(frozen=True)
class Manifest:
    """What ran, for one record: a trial (``code``, ``controller``, ``runtime`` and what it
    learnt from) or a drive (``robot``, ``driver``). Built by ``Manifest.trial`` or
    ``Manifest.drive``, or read from a record by ``from_json``; ``to_json`` writes it as
    records hold it, ``digest`` names it."""

    kind: Kind
    task: TaskVersion
    parameters: Mapping[str, Value]  # the task's full values, as written (sorted)
    seed: int
    versions: Versions
    model_sha256: str  # of the compiled model
    # a trial's
    code: Code | None = None
    controller: Controller | None = None
    runtime: str | None = None  # the sandbox runtime's digest
    data: tuple[Pinned, ...] = ()
    blind: bool = False  # a held-out episode: its controller was told no seed
    # a drive's
    robot: str | None = None
    driver: Driver | None = field(default=None)
    # a match leg's: each side's team, in the task's order of sides (and its runtime)
    teams: Mapping[str, Team] = field(default_factory=dict)

    def __post_init__(self) -> None:
        trial = (self.code, self.controller, self.runtime)
        drive = (self.robot, self.driver)
        if self.kind is Kind.TRIAL and (None in trial or drive != (None, None) or self.teams):
            raise ValueError("a trial's manifest has its code, controller and runtime only")
        if self.kind is Kind.DEMONSTRATION and (
            None in drive or trial != (None, None, None) or self.teams
        ):
            raise ValueError("a drive's manifest has its robot and driver only")
        if self.kind is Kind.DEMONSTRATION and (self.data or self.blind):
            raise ValueError("a drive learns from no data and is never blind")
        if self.kind is Kind.MATCH and (
            len(self.teams) < 2
            or self.runtime is None
            or (self.code, self.controller) != (None, None)
            or drive != (None, None)
            or self.data
            or self.blind
        ):
            raise ValueError("a match leg's manifest has two teams or more and a runtime only")

    # -- the two kinds --------------------------------------------------------------------

    @classmethod
    def trial(
        cls,
        *,
        code: Code,
        controller: Controller,
        task: TaskVersion,
        parameters: Mapping[str, Value],
        seed: int,
        runtime: str,
        versions: Versions,
        model_sha256: str,
        data: Sequence[PinnedRecord] = (),
        blind: bool = False,
    ) -> Manifest:
        """A controller's trial: the code and what was installed for it, in ``runtime``."""
        return cls(
            kind=Kind.TRIAL,
            task=task,
            parameters=dict(sorted(parameters.items())),
            seed=seed,
            versions=versions,
            model_sha256=model_sha256,
            code=code,
            controller=controller,
            runtime=runtime,
            data=tuple(Pinned.of(record) for record in data),
            blind=blind,
        )

    @classmethod
    def drive(
        cls,
        *,
        robot: str,
        task: TaskVersion,
        parameters: Mapping[str, Value],
        seed: int,
        driver: Driver,
        versions: Versions,
        model_sha256: str,
    ) -> Manifest:
        """A drive of the live robot ``robot``, on the wall clock."""
        return cls(
            kind=Kind.DEMONSTRATION,
            task=task,
            parameters=dict(sorted(parameters.items())),
            seed=seed,
            versions=versions,
            model_sha256=model_sha256,
            robot=robot,
            driver=driver,
        )

    @classmethod
    def match(
        cls,
        *,
        teams: Mapping[str, Team],
        task: TaskVersion,
        parameters: Mapping[str, Value],
        seed: int,
        runtime: str,
        versions: Versions,
        model_sha256: str,
    ) -> Manifest:
        """A leg of a match: each side's code and controller (``teams``, side -> team,
        in the task's order of sides), every one in ``runtime``, on one seed."""
        return cls(
            kind=Kind.MATCH,
            task=task,
            parameters=dict(sorted(parameters.items())),
            seed=seed,
            versions=versions,
            model_sha256=model_sha256,
            runtime=runtime,
            teams=dict(teams),
        )

    # -- what readers ask -----------------------------------------------------------------

    @property
    def repository(self) -> str | None:
        """The trial's repository (None for a drive)."""
        return None if self.code is None else self.code.repository

    @property
    def commit(self) -> str | None:
        """The trial's commit (None for a drive, and for code run from a folder)."""
        return None if self.code is None else self.code.commit

    @property
    def realtime(self) -> bool:
        """Whether it ran on the wall clock rather than in lockstep (a drive always; a
        match's leg never)."""
        if self.kind is Kind.MATCH:
            return False
        return True if self.controller is None else self.controller.realtime

    @property
    def live(self) -> bool:
        """A live robot's drive: its episode had no time limit."""
        return self.kind is Kind.DEMONSTRATION

    @property
    def digest(self) -> str:
        """The manifest digest, which names the experiment."""
        return manifest_digest(self.to_json())

    # -- written, and read ----------------------------------------------------------------

    def to_json(self) -> dict[str, Any]:
        """The manifest as records hold it: the same keys in the same order, byte for byte
        (its canonical JSON is what its digest is computed over)."""
        if self.kind is Kind.DEMONSTRATION:
            assert self.robot is not None and self.driver is not None
            return {
                "schema": SCHEMA,
                "kind": self.kind.value,
                "robot": self.robot,
                "task": self.task.to_json(),
                "parameters": dict(self.parameters),
                "seed": self.seed,
                "live": True,
                "controller": {"realtime": True},
                "driver": self.driver.to_json(),
                "versions": self.versions.to_json(),
                "model_sha256": self.model_sha256,
            }
        if self.kind is Kind.MATCH:
            return {
                "schema": SCHEMA,
                "kind": self.kind.value,
                "task": self.task.to_json(),
                "parameters": dict(self.parameters),
                "seed": self.seed,
                "teams": {side: team.to_json() for side, team in self.teams.items()},
                "runtime": self.runtime,
                "versions": self.versions.to_json(),
                "model_sha256": self.model_sha256,
            }
        assert self.code is not None and self.controller is not None
        out: dict[str, Any] = {
            "schema": SCHEMA,
            **self.code.to_json(),
            "task": self.task.to_json(),
            "parameters": dict(self.parameters),
            "seed": self.seed,
            "controller": self.controller.to_json(),
            "runtime": self.runtime,
            "versions": self.versions.to_json(),
            "model_sha256": self.model_sha256,
        }
        if self.data:  # the records it learnt from; without, manifests keep their digests
            out["data"] = [pinned.to_json() for pinned in self.data]
        if self.blind:  # a held-out episode (likewise, only then)
            out["blind"] = True
        return out

    @classmethod
    def from_json(cls, value: Mapping[str, Any]) -> Manifest:
        """The manifest a record holds (``ManifestError`` naming the key that is not as
        the lab writes it)."""
        top = _Reader(dict(value), "manifest")
        schema = top.text("schema")
        if schema != SCHEMA:
            raise ManifestError("manifest.schema", f"is {schema!r}; this lab reads {SCHEMA!r}")
        if top.has("kind"):
            kind = top.text("kind")
            if kind == Kind.MATCH.value:
                return cls._read_match(top)
            if kind != Kind.DEMONSTRATION.value:
                raise ManifestError(
                    "manifest.kind", f"is {kind!r}; only a drive's and a match's say their kind"
                )
            return cls._read_drive(top)
        return cls._read_trial(top)

    @classmethod
    def _read_trial(cls, top: _Reader) -> Manifest:
        code = Code.read(top)
        data: tuple[Pinned, ...] = ()
        if top.has("data"):
            entries = top.raw("data")
            if not isinstance(entries, list) or not entries:
                raise ManifestError("manifest.data", "is written only as a list of records")
            data = tuple(
                Pinned.read(_Reader(e, f"manifest.data[{n}]")) for n, e in enumerate(entries)
            )
        blind = top.has("blind")
        if blind:
            top.true("blind")
        found = cls(
            kind=Kind.TRIAL,
            task=TaskVersion.read(top.object("task")),
            parameters=_parameters(top.raw("parameters")),
            seed=top.integer("seed"),
            versions=Versions.read(top.object("versions")),
            model_sha256=top.text("model_sha256"),
            code=code,
            controller=Controller.read(top.object("controller")),
            runtime=top.text("runtime"),
            data=data,
            blind=blind,
        )
        top.done()
        return found

    @classmethod
    def _read_drive(cls, top: _Reader) -> Manifest:
        top.true("live")
        controller = top.object("controller")
        controller.true("realtime")
        controller.done()
        found = cls(
            kind=Kind.DEMONSTRATION,
            task=TaskVersion.read(top.object("task")),
            parameters=_parameters(top.raw("parameters")),
            seed=top.integer("seed"),
            versions=Versions.read(top.object("versions")),
            model_sha256=top.text("model_sha256"),
            robot=top.text("robot"),
            driver=Driver.read(top.object("driver")),
        )
        top.done()
        return found

    @classmethod
    def _read_match(cls, top: _Reader) -> Manifest:
        sides = top.object("teams")
        teams = {side: Team.read(sides.object(side)) for side in list(sides.value)}
        if len(teams) < 2:
            raise ManifestError("manifest.teams", "must name two sides or more")
        found = cls(
            kind=Kind.MATCH,
            task=TaskVersion.read(top.object("task")),
            parameters=_parameters(top.raw("parameters")),
            seed=top.integer("seed"),
            versions=Versions.read(top.object("versions")),
            model_sha256=top.text("model_sha256"),
            runtime=top.text("runtime"),
            teams=teams,
        )
        top.done()
        return found


def _parameters(value: Any) -> dict[str, Value]:
    if not isinstance(value, dict):
        raise ManifestError("manifest.parameters", f"must be an object, not {_shown(value)}")
    for name, item in value.items():
        if not isinstance(item, bool | int | float | str):
            raise ManifestError(
                f"manifest.parameters.{name}",
                f"must be a number, true, false or a string, not {_shown(item)}",
            )
    return dict(value)
