"""The trial runner: one controller, one robot, one recording, one outcome.

``run_trial`` checks the code out, reads ``lab.toml``, installs the requirements (a
build step with the package index as its only network, cached by the file's hash),
starts the task in lockstep with a bridge session private to the trial (on a unix
socket the sandbox reaches as ``ws://127.0.0.1:9090``), records every topic, starts the
sandboxed controller, and stops everything when the first of these happens:

- the episode ends (the controller gets a moment to exit by itself);
- the controller exits;
- the controller stalls: no ``/lab/step`` for ``stall`` seconds (``first_step``
  before the first one, for imports and connecting);
- a sandbox limit is hit (time, memory, output, CPU).

The outcome says whether the trial ran to its end (``succeeded``), broke (``failed``,
with a reason a person can act on) or was stopped (``cancelled``); whether the robot
did its task is in the metrics.
"""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import json
import logging
import shutil
import tempfile
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from labd.bridge.rosapi import Rosapi
from labd.bridge.server import BridgeServer
from labd.config import BridgeConfig
from labd.errors import LabError
from labd.graph.graph import Graph
from labd.graph.types import TypeRegistry
from labd.recorder import Recorder
from labd.sim import registry
from labd.sim.robot import LiveRunner, Robot
from sandbox.api import Backend, Exit, InstallError, Job, Limits, Running, SandboxError
from scheduler import controller as controller_config
from scheduler import manifest as manifests
from scheduler.errors import ControllerConfigError, RequirementsError, TrialError
from scheduler.fetch import FetchPolicy
from scheduler.outcome import CANCELLED, FAILED, Outcome, judge
from scheduler.source import checkout

log = logging.getLogger("scheduler.runner")


@dataclass(frozen=True)
class TrialSpec:
    """What to run: the code, the task (default: lab.toml's), its parameters and seed."""

    source: str
    ref: str | None = None
    task: str | None = None
    params: Mapping[str, Any] = field(default_factory=dict)
    seed: int = 0


@dataclass(frozen=True)
class RunOptions:
    limits: Limits = field(default_factory=Limits)
    stall: float = 10.0  # seconds without /lab/step
    first_step: float = 60.0  # seconds to the first /lab/step
    grace: float = 2.0  # after the episode ends, for the controller to exit by itself
    fetch: FetchPolicy | None = None  # the lab's; None: labd run (local folders from disk)


@dataclass
class TrialResult:
    status: str
    reason: str
    folder: Path
    manifest: dict[str, Any] = field(default_factory=dict)
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
    def mcap(self) -> Path | None:
        path = self.folder / "trial.mcap"
        return path if path.exists() else None

    def to_json(self) -> dict[str, Any]:
        return {
            "status": self.status,
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
            "manifest": self.manifest,
        }


async def run_trial(
    spec: TrialSpec,
    *,
    backend: Backend,
    out: Path,
    cache: Path,
    types: TypeRegistry,
    options: RunOptions | None = None,
) -> TrialResult:
    """Run one trial into the folder ``out``.

    A trial that cannot start (no lab.toml, an unknown task, requirements that do not
    install...) is a failed trial with the reason, not an exception.
    """
    options = options or RunOptions()
    loop = asyncio.get_running_loop()
    started = loop.time()
    work = Path(tempfile.mkdtemp(prefix="labd-trial-"))
    work.chmod(0o755)  # the sandbox's unprivileged user reads the code below it
    out.mkdir(parents=True, exist_ok=True)
    try:
        code = work / "code"
        source = await asyncio.to_thread(
            checkout, spec.source, spec.ref, code, cache, options.fetch
        )
        config = controller_config.load(code)
        task = spec.task or config.task
        if task is None:
            raise ControllerConfigError("it names no task and none was given (--task)")
        values = registry.validate(task, spec.params)
        python_paths, requirements_sha = [], None
        if config.requirements:
            target, requirements_sha = await install_requirements(
                backend, code / config.requirements, cache
            )
            python_paths.append(target)
        trial = _Trial(
            spec=spec,
            config=config,
            task=task,
            values=values,
            types=types,
            backend=backend,
            options=options,
            work=work,
            out=out,
        )
        result = await trial.run(source, python_paths, requirements_sha)
    except (TrialError, LabError, SandboxError) as err:
        # The trial could not start: it is failed, with the reason, and has no record.
        log.info("trial of %s could not start: %s", spec.source, err)
        result = TrialResult(FAILED, str(err), out, backend=backend.name)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    result.wall_seconds = loop.time() - started
    (out / "result.json").write_text(json.dumps(result.to_json(), indent=2) + "\n")
    return result


async def install_requirements(backend: Backend, file: Path, cache: Path) -> tuple[Path, str]:
    """Install a requirements file into a folder cached by its hash and the runtime's."""
    sha = hashlib.sha256(file.read_bytes()).hexdigest()
    key = hashlib.sha256(f"{sha}:{backend.runtime_digest()}".encode()).hexdigest()[:32]
    target = cache / "requirements" / key
    if target.is_dir():
        return target, sha
    partial = target.with_name(target.name + ".partial")
    shutil.rmtree(partial, ignore_errors=True)
    partial.mkdir(parents=True)
    try:
        await backend.install(file, partial)
    except InstallError as err:
        shutil.rmtree(partial, ignore_errors=True)
        raise RequirementsError(err.reason, err.log) from None
    partial.rename(target)
    return target, sha


class _Trial:
    """The parts of one running trial, and their orderly end."""

    def __init__(
        self,
        *,
        spec: TrialSpec,
        config: controller_config.ControllerConfig,
        task: str,
        values: dict[str, Any],
        types: TypeRegistry,
        backend: Backend,
        options: RunOptions,
        work: Path,
        out: Path,
    ) -> None:
        self.spec = spec
        self.config = config
        self.task = task
        self.values = values
        self.backend = backend
        self.options = options
        self.work = work
        self.out = out
        self.graph = Graph(types, name="trial")
        limit = float(values["time_limit"]) if config.realtime else None
        self.robot = Robot(
            self.graph, task, values, spec.seed, live=config.realtime, time_limit=limit
        )
        self.rosapi = Rosapi(self.graph, BridgeConfig().protected_prefixes)
        self.ticked = asyncio.Event()
        self.robot.on_tick = self._tick
        self.launched: float | None = None  # loop time the sandbox was started
        self.first_step: float | None = None

    def _tick(self) -> None:
        if self.first_step is None:
            self.first_step = asyncio.get_running_loop().time()
        self.ticked.set()

    def digest_topics(self) -> set[str]:
        task = self.robot.sim.task
        names = {o.name for o in task.observations} | {c.name for c in task.commands}
        return names | {"/clock", "/lab/episode"}

    async def run(
        self, source: Any, python_paths: list[Path], requirements_sha: str | None
    ) -> TrialResult:
        sim = self.robot.sim
        manifest = manifests.build(
            source=source,
            controller=self.config,
            task=self.task,
            task_version=sim.spec.version,
            parameters=self.values,
            seed=self.spec.seed,
            runtime=self.backend.runtime_digest(),
            requirements_sha256=requirements_sha,
            model_sha256=sim.model_digest(),
        )
        digest = manifests.digest(manifest)
        socket_dir = self.work / "bridge"
        socket_dir.mkdir()
        socket_dir.chmod(0o755)
        bridge = BridgeServer({"trial": self.graph}, BridgeConfig(port=0, max_connections=16))
        recorder = Recorder(
            self.graph, self.out, digest_topics=self.digest_topics(), manifest=manifest
        )
        running: Running | None = None
        exit_: Exit | None = None
        outcome = Outcome(FAILED, "the trial did not start")
        live: asyncio.Task[None] | None = None
        try:
            await bridge.start(unix_path=socket_dir / "bridge.sock")
            (socket_dir / "bridge.sock").chmod(0o777)
            self.robot.publish()  # tick 0, now that the recorder listens
            if self.config.realtime:
                live = asyncio.create_task(LiveRunner(self.robot).run())
            self.launched = asyncio.get_running_loop().time()
            running = await self.backend.start(self._job(socket_dir / "bridge.sock", python_paths))
            exit_, outcome = await self._watch(running)
        except asyncio.CancelledError:
            outcome = Outcome(CANCELLED, "the trial was cancelled")
            if running is not None:
                exit_ = await running.stop()
            raise
        finally:
            if live is not None:
                live.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await live
            await bridge.close()
            metrics = self.robot.sim.metrics()
            result = TrialResult(
                outcome.status,
                outcome.reason,
                self.out,
                manifest,
                digest,
                metrics=metrics,
                backend=self.backend.name,
                exit_code=exit_.code if exit_ else None,
            )
            now = asyncio.get_running_loop().time()
            if self.launched is not None and self.first_step is not None:
                result.start_seconds = round(self.first_step - self.launched, 4)
                result.run_seconds = round(now - self.first_step, 4)
            summary = recorder.finish(attachments=self._attachments(manifest, exit_, result))
            result.data_digest = summary.data_digest
            result.digest_topics = sorted(self.digest_topics())
            self.robot.close()
            self.rosapi.close()
        return result

    def _job(self, socket: Path, python_paths: list[Path]) -> Job:
        env = {
            "LAB_TASK": self.task,
            "LAB_SEED": str(self.spec.seed),
            "LAB_PARAMS": json.dumps(self.values, sort_keys=True),
        }
        return Job(
            command=self.config.command,
            code=self.work / "code",
            bridge_socket=socket,
            env=env,
            python_paths=python_paths,
            limits=self.options.limits,
        )

    async def _watch(self, running: Running) -> tuple[Exit, Outcome]:
        """Wait for the first thing that ends the trial; stop the controller; judge."""
        exit_task = asyncio.create_task(running.wait())
        sim = self.robot.sim
        while True:
            if not self.robot.sim.running:
                try:
                    exit_ = await asyncio.wait_for(asyncio.shield(exit_task), self.options.grace)
                except TimeoutError:
                    exit_ = await running.stop()
                return exit_, judge(exit_, self.robot.sim, ended=True, limits=self.options.limits)
            stall = self.options.first_step if sim.tick == 0 else self.options.stall
            if self.config.realtime:
                stall = self.options.limits.wall
            self.ticked.clear()
            waiter = asyncio.create_task(self.ticked.wait())
            done, _ = await asyncio.wait(
                {exit_task, waiter}, timeout=stall, return_when=asyncio.FIRST_COMPLETED
            )
            waiter.cancel()
            if exit_task in done:
                exit_ = exit_task.result()
                return exit_, judge(
                    exit_,
                    self.robot.sim,
                    ended=not self.robot.sim.running,
                    limits=self.options.limits,
                )
            if not done:
                exit_ = await running.stop()
                return exit_, Outcome(
                    FAILED,
                    f"stalled at tick {self.robot.sim.tick}: no /lab/step for {stall:g} s",
                )

    def _attachments(
        self, manifest: dict[str, Any], exit_: Exit | None, result: TrialResult
    ) -> dict[str, tuple[str, bytes]]:
        sim = self.robot.sim
        files: dict[str, tuple[str, bytes]] = {
            "manifest.json": ("application/json", _json(manifest)),
            "outcome.json": (
                "application/json",
                _json(
                    {
                        "status": result.status,
                        "reason": result.reason,
                        "metrics": result.metrics,
                        "exit_code": result.exit_code,
                    }
                ),
            ),
            "lab.toml": ("application/toml", self.config.text.encode()),
            "model.xml": ("application/xml", sim.model_xml().encode()),
        }
        for name, data in sim.task.model_assets.items():
            files[f"model/{name}"] = ("application/octet-stream", data)
        if exit_ is not None:
            files["controller.stdout.log"] = ("text/plain", exit_.stdout)
            files["controller.stderr.log"] = ("text/plain", exit_.stderr)
            (self.out / "controller.stdout.log").write_bytes(exit_.stdout)
            (self.out / "controller.stderr.log").write_bytes(exit_.stderr)
        (self.out / "manifest.json").write_bytes(_json(manifest))
        return files


def _json(value: Any) -> bytes:
    return (json.dumps(value, indent=2, sort_keys=True) + "\n").encode()
