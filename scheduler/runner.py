"""The trial runner: one controller, one robot, one recording, one ending.

``run_trial`` checks the code out, reads ``lab.toml``, installs the requirements (a
build step with the package index as its only network, cached by the file's hash),
opens the lab side of the trial (``scheduler.host``: the task in lockstep with a bridge
session private to the trial, on a unix socket the sandbox reaches as
``ws://127.0.0.1:9090``, and a recorder), starts the sandboxed controller, and stops
everything when the first of these happens:

- the episode ends (the controller gets a moment to exit by itself);
- the controller exits;
- the controller stalls: no ``/lab/step`` for ``stall`` seconds (``first_step``
  before the first one, for imports and connecting);
- a sandbox limit is hit (time, memory, output, CPU).

Its ending (``repository.trial.Ending``) is ``success`` when the task was achieved,
``fail`` when the trial ran to its end without achieving it, ``error`` when it broke
(it could not start, crashed, stalled, hit a limit), or ``cancelled``. Each stage has
a deadline, reported in ``Progress`` so that a worker can tell a trial that still moves
from one that is stuck.
"""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import json
import logging
import shutil
import tempfile
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from repository.digests import readable_json
from repository.errors import ArchiveError
from repository.manifest import Code, Manifest
from repository.trial import Ending, Order, Outcome, Status, Value
from repository.units import MiB
from repository.well_known import LOGS, MANIFEST, OUTCOME, RECORD_FILE
from sandbox.api import Backend, Exit, InstallError, Job, Limits, Running, SandboxError
from sandbox.runtime import NODE_MODULES, PROVIDED_NODE_PACKAGES
from scheduler import controller as controller_config
from scheduler.controller import LOCK, PACKAGE
from scheduler.data import Archive, Blobs, materialize, resolve
from scheduler.errors import (
    ControllerConfigError,
    DataUnavailable,
    NodePackagesError,
    QueueError,
    RequirementsError,
    TrialError,
)
from scheduler.fetch import FetchPolicy
from scheduler.files import RepositoryFiles
from scheduler.host import TrialHost, TrialLab, TrialSetup
from scheduler.outcome import judge, storage_failure
from scheduler.source import checkout
from scheduler.states import Stage

log = logging.getLogger("scheduler.runner")


@dataclass(frozen=True)
class RunOptions:
    limits: Limits = field(default_factory=Limits)
    stall: float = 10.0  # seconds without /lab/step
    first_step: float = 60.0  # seconds to the first /lab/step
    grace: float = 2.0  # after the episode ends, for the controller to exit by itself
    prepare: float = 900.0  # seconds to check out, read lab.toml and install requirements
    slack: float = 30.0  # seconds past the controller's limits before a trial counts as stuck
    fetch: FetchPolicy | None = None  # the lab's; None: labd run (local folders from disk)

    @property
    def run_deadline(self) -> float:
        """The longest a started controller may take before the trial must be over."""
        return self.limits.wall + self.first_step + self.grace + self.slack


class Progress:
    """Which stage a trial is in, since when, and until when it may stay there.

    The runner moves it on; a worker reads it to show what it does, and to notice a
    trial stuck past its stage's deadline (then its lease is no longer renewed).
    """

    def __init__(self, clock: Any = time.monotonic) -> None:
        self.clock = clock
        self.stage = Stage.STARTING
        self.since = clock()
        self.deadline = self.since + 60.0

    def enter(self, stage: Stage, seconds: float) -> None:
        self.stage = stage
        self.since = self.clock()
        self.deadline = self.since + seconds

    @property
    def elapsed(self) -> float:
        return float(self.clock() - self.since)

    def overdue(self) -> float:
        """Seconds past the stage's deadline (0 while on time)."""
        return max(0.0, float(self.clock() - self.deadline))


@dataclass
class TrialResult:
    ending: Ending
    folder: Path
    manifest: Manifest | None = None  # None: the trial did not start
    manifest_digest: str = ""
    data_digest: str = ""
    metrics: dict[str, Any] = field(default_factory=dict)
    backend: str = ""
    exit_code: int | None = None
    wall_seconds: float = 0.0
    start_seconds: float | None = None  # from starting the sandbox to the first /lab/step
    run_seconds: float | None = None  # from the first /lab/step to the end
    digest_topics: list[str] = field(default_factory=list)  # what data_digest covers

    @property
    def status(self) -> Status:
        return self.ending.status

    @property
    def outcome(self) -> Outcome | None:
        return self.ending.outcome

    @property
    def reason(self) -> str:
        return self.ending.reason

    @property
    def mcap(self) -> Path | None:
        path = self.folder / RECORD_FILE
        return path if path.exists() else None

    def to_json(self) -> dict[str, Any]:
        return {
            "status": self.status.value,
            "outcome": self.outcome.value if self.outcome else None,
            "reason": self.reason,
            "manifest_digest": self.manifest_digest,
            "data_digest": self.data_digest,
            "metrics": self.metrics,
            "mcap": str(self.mcap) if self.mcap else None,
            "folder": str(self.folder),
            "backend": self.backend,
            "exit_code": self.exit_code,
            "wall_seconds": round(self.wall_seconds, 3),
            "start_seconds": self.start_seconds,
            "run_seconds": self.run_seconds,
            "manifest": self.manifest.to_json() if self.manifest is not None else {},
        }


async def run_trial(
    order: Order,
    *,
    blind: bool = False,
    backend: Backend,
    host: TrialHost,
    out: Path,
    cache: Path,
    options: RunOptions | None = None,
    progress: Progress | None = None,
    archive: Blobs | None = None,
    resolver: Archive | None = None,
) -> TrialResult:
    """Run ``order`` into the folder ``out``: its code at its commit (or, not resolved
    yet, at its ref), its task (or lab.toml's), parameters and seed.

    ``blind``: a held-out episode, whose controller is told nothing of the seed (no
    ``LAB_SEED``, and ``/lab/episode`` says 0); the manifest says so, and its replay and
    reruns run blind too. ``archive`` is where the records ``order.data`` pins are
    fetched from (a lab's blob store, or its HTTP API); ``resolver`` is where lab.toml's
    ``[data]`` is resolved when the order pins nothing yet (``labd run``: a local
    archive, or a lab's API). A
    trial that cannot start (no lab.toml, an unknown task, requirements that do not
    install, pinned data that is gone or changed...) ends as an ``error`` with the
    reason, not with an exception.
    """
    options = options or RunOptions()
    progress = progress or Progress()
    out, cache = out.resolve(), cache.resolve()  # a sandbox engine mounts absolute paths

    async def attempt(work: Path) -> TrialResult:
        try:
            progress.enter(Stage.PREPARING, options.prepare)
            try:
                prepared = await asyncio.wait_for(
                    prepare(
                        order,
                        blind=blind,
                        backend=backend,
                        host=host,
                        work=work,
                        cache=cache,
                        options=options,
                        archive=resolver or archive,
                        resolver=resolver,
                    ),
                    options.prepare,
                )
            except TimeoutError:
                raise TrialError(
                    f"preparing the trial (checking out, reading lab.toml, installing the"
                    f" requirements, fetching its data) took longer than {options.prepare:g} s"
                ) from None
            trial = _Trial(prepared, backend=backend, options=options, work=work, out=out)
            progress.enter(Stage.RUNNING, options.run_deadline)
            return await trial.run()
        except (TrialError, SandboxError) as err:
            # The trial could not start: an error, with the reason, and no record.
            log.info("trial of %s could not start: %s", order.repository, err)
            return TrialResult(Ending.error(str(err)), out, backend=backend.name)

    return await in_work_folder(out, "trial", attempt)


async def in_work_folder(
    out: Path, what: str, attempt: Callable[[Path], Awaitable[TrialResult]]
) -> TrialResult:
    """``attempt`` given a fresh work folder (removed after), timed, and its result also
    written to ``out/result.json`` (a disk too full for that makes it the lab's error)."""
    loop = asyncio.get_running_loop()
    started = loop.time()
    work = Path(tempfile.mkdtemp(prefix=f"labd-{what}-"))
    work.chmod(0o755)  # the sandbox's unprivileged user reads the code below it
    out.mkdir(parents=True, exist_ok=True)
    try:
        result = await attempt(work)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    result.wall_seconds = loop.time() - started
    try:
        write_whole(out / "result.json", (json.dumps(result.to_json(), indent=2) + "\n").encode())
    except OSError as err:
        reason = storage_failure(err, f"the {what}'s result could not be written")
        log.error("%s in %s: %s", what, out, reason)
        if result.outcome is not Outcome.ERROR:
            result.ending = Ending.lab_error(reason)
    return result


@dataclass
class Prepared:
    """A trial ready to start: its order resolved (the commit checked out, the task,
    the records it learns from pinned), its code and what was installed for it."""

    order: Order  # task and commit resolved
    blind: bool
    code: Code
    config: controller_config.ControllerConfig
    values: dict[str, Value]  # the task's parameters, every one
    host: TrialHost
    python_paths: list[Path]
    requirements_sha: str | None
    data: Path | None = None  # the folder mounted at LAB_DATA_DIR
    node_modules: Path | None = None  # the installed npm packages, mounted at /node_modules
    node_packages_sha: str | None = None  # sha256 of package-lock.json

    @property
    def task(self) -> str:
        assert self.order.task is not None  # resolved by ``_prepare``
        return self.order.task


async def prepare(
    order: Order,
    *,
    blind: bool,
    backend: Backend,
    host: TrialHost,
    work: Path,
    cache: Path,
    options: RunOptions,
    archive: Blobs | None,
    resolver: Archive | None = None,
) -> Prepared:
    ref = order.commit or order.ref  # a queued trial's pinned commit; labd run's ref
    checked_out = work / "code"
    code = await asyncio.to_thread(
        checkout, order.repository, ref, checked_out, cache, options.fetch
    )
    config = controller_config.load(checked_out)
    task = order.task or config.task
    if task is None:
        raise ControllerConfigError("it names no task and none was given (--task)")
    values = host.check(task, order.params)
    python_paths, requirements_sha = [], None
    if config.requirements:
        target, requirements_sha = await install_requirements(
            backend, checked_out, config.requirements, cache
        )
        python_paths.append(target)
    node_modules, node_sha = None, None
    if config.node_packages:
        node_modules, node_sha = await install_node_packages(backend, checked_out, cache)
    pinned = order.data
    data = None
    if config.data is not None and not pinned:
        if resolver is None:
            raise ControllerConfigError(
                "it has [data], but no data was pinned for this trial and there is no archive"
                " to resolve it against (labd run: --server URL, or --data with a lab's archive)"
            )
        try:
            pinned = tuple(await asyncio.to_thread(resolve, config.data, resolver))
        except (QueueError, ArchiveError) as err:  # nothing to pin, too much, unreachable
            raise TrialError(str(err)) from None
    if pinned:
        if archive is None:
            raise DataUnavailable(
                pinned[0].trial, "cannot be fetched: this runner has no archive to read it from"
            )
        data = await asyncio.to_thread(materialize, pinned, archive, host, cache)
    resolved = order.model_copy(update={"commit": code.commit or "", "task": task, "data": pinned})
    return Prepared(
        resolved,
        blind,
        code,
        config,
        values,
        host,
        python_paths,
        requirements_sha,
        data,
        node_modules,
        node_sha,
    )


async def install_requirements(
    backend: Backend, code: Path, name: str, cache: Path
) -> tuple[Path, str]:
    """Install the checkout's requirements file ``name`` into a folder cached by its hash
    and the runtime's (the file is read as the repository's own, never through a link)."""
    sha = hashlib.sha256(RepositoryFiles(code).read_bytes(name)).hexdigest()
    key = hashlib.sha256(f"{sha}:{backend.runtime_digest()}".encode()).hexdigest()[:32]

    async def install(partial: Path) -> None:
        try:
            await backend.install(code / name, partial)
        except InstallError as err:
            raise RequirementsError(err.reason, err.log) from None

    return await _installed(cache / "requirements" / key, install), sha


MAX_LOCK = 32 * MiB  # bytes of package.json or package-lock.json the lab reads


async def install_node_packages(backend: Backend, code: Path, cache: Path) -> tuple[Path, str]:
    """``npm ci`` of the checkout's package.json and package-lock.json into a folder cached
    by their digests and the runtime's; returns its ``node_modules`` and the lock's sha256.

    What every controller is given (``roslib``) is added where the lock has none of it.
    """
    files = RepositoryFiles(code, limit=MAX_LOCK)
    package, lock = files.read_bytes(PACKAGE), files.read_bytes(LOCK)
    sha = hashlib.sha256(lock).hexdigest()
    inputs = f"{hashlib.sha256(package).hexdigest()}:{sha}:{backend.runtime_digest()}"
    key = hashlib.sha256(inputs.encode()).hexdigest()[:32]

    async def install(partial: Path) -> None:
        try:
            await backend.install_node(code / PACKAGE, code / LOCK, partial)
        except InstallError as err:
            raise NodePackagesError(err.reason, err.log) from None
        modules = partial / "node_modules"
        modules.mkdir(exist_ok=True)
        for name in PROVIDED_NODE_PACKAGES:
            if not (modules / name).exists():
                (modules / name).symlink_to(f"{NODE_MODULES}/{name}")

    return await _installed(cache / "node" / key, install) / "node_modules", sha


async def _installed(target: Path, install: Callable[[Path], Awaitable[None]]) -> Path:
    """``target``, made by ``install`` into a partial folder renamed into place unless it
    is there already; a failed install leaves nothing behind."""
    if target.is_dir():
        return target
    partial = target.with_name(target.name + ".partial")
    shutil.rmtree(partial, ignore_errors=True)
    partial.mkdir(parents=True)
    try:
        await install(partial)
    except BaseException:
        shutil.rmtree(partial, ignore_errors=True)
        raise
    partial.rename(target)
    return target


class _Trial:
    """The parts of one running trial, and their orderly end."""

    def __init__(
        self, prepared: Prepared, *, backend: Backend, options: RunOptions, work: Path, out: Path
    ) -> None:
        self.prepared = prepared
        self.backend = backend
        self.options = options
        self.work = work
        self.out = out
        order, config = prepared.order, prepared.config
        setup = TrialSetup(
            task=prepared.task,
            values=prepared.values,
            seed=order.seed,
            code=prepared.code,
            controller=config.in_manifest(
                requirements_sha256=prepared.requirements_sha,
                node_packages_sha256=prepared.node_packages_sha,
            ),
            runtime=backend.runtime_digest(),
            data=order.data,
            blind=prepared.blind,
            interfaces=config.interface_files,
        )
        self.lab: TrialLab = prepared.host.open(setup, out=out)
        self.launched: float | None = None  # loop time the sandbox was started
        self.first_step: float | None = None

    async def run(self) -> TrialResult:
        lab = self.lab
        manifest = lab.manifest
        digest = manifest.digest
        socket_dir = self.work / "bridge"
        socket_dir.mkdir()
        socket_dir.chmod(0o755)
        running: Running | None = None
        exit_: Exit | None = None
        ending = Ending.error("the trial did not start")
        try:
            await lab.start(socket_dir / "bridge.sock")
            (socket_dir / "bridge.sock").chmod(0o777)
            self.launched = asyncio.get_running_loop().time()
            running = await self.backend.start(self._job(socket_dir / "bridge.sock"))
            exit_, ending = await self._watch(running)
        except asyncio.CancelledError:
            ending = Ending.cancelled("the trial was cancelled")
            if running is not None:
                exit_ = await running.stop()
            raise
        finally:
            result = TrialResult(
                ending,
                self.out,
                manifest,
                digest,
                metrics=lab.metrics(),
                backend=self.backend.name,
                exit_code=exit_.code if exit_ else None,
            )
            now = asyncio.get_running_loop().time()
            if self.launched is not None and self.first_step is not None:
                result.start_seconds = round(self.first_step - self.launched, 4)
                result.run_seconds = round(now - self.first_step, 4)
            failed = None  # the lab could not write the record: the trial is an error
            try:
                result.data_digest = await lab.finish(self._attachments(manifest, exit_, result))
                result.digest_topics = sorted(lab.digest_topics)
            except TrialError as err:  # the disk filled up: the record was deleted
                failed = str(err)
            try:
                self._write_files(manifest, exit_)
            except OSError as err:
                failed = failed or storage_failure(err, "the trial's files could not be written")
            if failed is not None:
                log.error("trial in %s: %s", self.out, failed)
                result.ending = Ending.lab_error(failed)
        return result

    def _job(self, socket: Path) -> Job:
        return job_of(self.prepared, self.work / "code", socket, self.options.limits)

    async def _watch(self, running: Running) -> tuple[Exit, Ending]:
        """Wait for the first thing that ends the trial; stop the controller; judge."""
        exit_task = asyncio.create_task(running.wait())
        lab = self.lab
        limits = self.options.limits
        loop = asyncio.get_running_loop()
        watching = loop.time()
        while True:
            episode = lab.episode()
            if self.first_step is None and lab.first_tick_at is not None:
                self.first_step = lab.first_tick_at
            if not episode.running:
                try:
                    exit_ = await asyncio.wait_for(asyncio.shield(exit_task), self.options.grace)
                except TimeoutError:
                    exit_ = await running.stop()
                return exit_, judge(exit_, lab.episode(), ended=True, limits=limits)
            stall = self.options.first_step if episode.tick == 0 else self.options.stall
            if self.prepared.config.realtime:
                stall = limits.wall
            # Woken when the episode ends, the controller exits, or no step has come
            # for ``stall`` seconds; not every tick.
            last = lab.last_tick_at
            quiet = loop.time() - (watching if last is None else max(watching, last))
            if quiet >= stall:
                exit_ = await running.stop()
                tick = lab.episode().tick
                return exit_, Ending.error(f"stalled at tick {tick}: no /lab/step for {stall:g} s")
            waiter = asyncio.create_task(lab.ended())
            done, _ = await asyncio.wait(
                {exit_task, waiter}, timeout=stall - quiet, return_when=asyncio.FIRST_COMPLETED
            )
            waiter.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await waiter
            if exit_task in done:
                exit_ = exit_task.result()
                episode = lab.episode()
                return exit_, judge(exit_, episode, ended=not episode.running, limits=limits)

    def _attachments(
        self, manifest: Manifest, exit_: Exit | None, result: TrialResult
    ) -> dict[str, tuple[str, bytes]]:
        files: dict[str, tuple[str, bytes]] = {
            **said_files(manifest, result),
            "lab.toml": ("application/toml", self.prepared.config.text.encode()),
            **self.lab.model_files(),
        }
        if exit_ is not None:
            files[LOGS["stdout"]] = ("text/plain", exit_.stdout)
            files[LOGS["stderr"]] = ("text/plain", exit_.stderr)
        return files

    def _write_files(self, manifest: Manifest, exit_: Exit | None) -> None:
        """The record's folder beside the MCAP: the manifest and the controller's logs."""
        if exit_ is not None:
            write_whole(self.out / LOGS["stdout"], exit_.stdout)
            write_whole(self.out / LOGS["stderr"], exit_.stderr)
        write_whole(self.out / MANIFEST, readable_json(manifest.to_json()))


def said_files(manifest: Manifest, result: TrialResult) -> dict[str, tuple[str, bytes]]:
    """A record's manifest and outcome attachments, as people and the filing check read them."""
    outcome = {
        "status": result.status.value,
        "outcome": result.outcome.value if result.outcome else None,
        "reason": result.reason,
        "metrics": result.metrics,
        "exit_code": result.exit_code,
    }
    return {
        MANIFEST: ("application/json", readable_json(manifest.to_json())),
        OUTCOME: ("application/json", readable_json(outcome)),
    }


def job_of(p: Prepared, code: Path, socket: Path, limits: Limits) -> Job:
    """The sandbox job of the prepared controller checked out at ``code``, reaching its
    bridge through ``socket``."""
    env = {"LAB_TASK": p.task, "LAB_PARAMS": json.dumps(p.values, sort_keys=True)}
    if not p.blind:  # a held-out episode's seed never reaches its controller
        env["LAB_SEED"] = str(p.order.seed)
    return Job(
        command=p.config.command,
        code=code,
        bridge_socket=socket,
        env=env,
        python_paths=p.python_paths,
        limits=limits,
        data=p.data,
        node_modules=p.node_modules,
    )


def write_whole(path: Path, data: bytes) -> None:
    """Write a file whole or not at all: a full disk leaves no half file to be filed."""
    tmp = path.with_name(f".{path.name}.tmp")
    try:
        tmp.write_bytes(data)
        tmp.replace(path)
    finally:
        tmp.unlink(missing_ok=True)
