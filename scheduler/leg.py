"""One leg of a match: a controller on each side, one station, one ending.

``run_leg`` prepares every side's team as ``run_trial`` prepares a controller (the
checkout, ``lab.toml``, its requirements and node packages), opens the lab side of the
leg (``scheduler.host.MatchLab``: the task behind a step barrier, a bridge for each
side on a socket of its own, one recorder), starts every side's sandbox together, and
stops everything at the first of these:

- the episode ends (a goal, the time limit): the leg has its result, and each side a
  moment (``grace``) to exit by itself;
- a side exits, whatever its code, or is stopped by a sandbox limit: it forfeits;
- a side owes a step for longer than the deadline (``step_deadline`` after the last
  tick, ``first_step`` from the start before the first one): it forfeits.

A side that forfeits loses the leg and the record ends at the last tick both sides
stepped, so it replays like any other. Every side failing leaves no result (an
error). A team that cannot be prepared (its checkout, ``lab.toml``, its requirements:
the same at its pinned commit in every leg it plays) leaves the leg unplayed, without a
record and without a result: an error that names it. The leg's result is in its metrics
(``scheduler.outcome.judge_leg``): ``winner``, ``ended_by``, ``forfeited``, beside the
task's own (soccer's ``home_goals`` and ``away_goals``: a task teams play says each
side's goals as ``SIDE_goals``).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

from repository.digests import readable_json
from repository.manifest import Manifest, Team
from repository.match import STEP_DEADLINE
from repository.trial import Ending, Order, Value
from repository.well_known import MANIFEST, side_logs
from sandbox.api import Backend, Exit, Running, SandboxError
from scheduler.errors import ControllerConfigError, InvalidRequest, TrialError
from scheduler.host import MatchLab, MatchSetup, TrialHost
from scheduler.outcome import judge, judge_leg, storage_failure
from scheduler.runner import (
    Prepared,
    Progress,
    RunOptions,
    TrialResult,
    in_work_folder,
    job_of,
    prepare,
    said_files,
    write_whole,
)
from scheduler.states import Stage

log = logging.getLogger("scheduler.leg")


@dataclass(frozen=True)
class LegOptions:
    """A trial's options, and how long a side may keep the other waiting."""

    run: RunOptions = field(default_factory=RunOptions)
    step_deadline: float = STEP_DEADLINE


async def run_leg(
    orders: Mapping[str, Order],
    *,
    backend: Backend,
    host: TrialHost,
    out: Path,
    cache: Path,
    options: LegOptions | None = None,
    progress: Progress | None = None,
) -> TrialResult:
    """Play one leg: ``orders`` are each side's team (side -> order, in the task's
    order of sides), all of the same task, parameters and seed. Its record goes into
    the folder ``out``; a leg that cannot be played ends as an ``error`` with the
    reason, not with an exception."""
    options = options or LegOptions()
    progress = progress or Progress()
    out, cache = out.resolve(), cache.resolve()

    async def attempt(work: Path) -> TrialResult:
        return await _play(
            orders,
            backend=backend,
            host=host,
            work=work,
            out=out,
            cache=cache,
            options=options,
            progress=progress,
        )

    return await in_work_folder(out, "leg", attempt)


async def _play(
    orders: Mapping[str, Order],
    *,
    backend: Backend,
    host: TrialHost,
    work: Path,
    out: Path,
    cache: Path,
    options: LegOptions,
    progress: Progress,
) -> TrialResult:
    first = next(iter(orders.values()))
    task = first.task
    if task is None or any(
        (o.task, o.params, o.seed) != (task, first.params, first.seed) for o in orders.values()
    ):
        raise ValueError("a leg's orders name one task, its parameters and seed")
    try:
        sides = tuple(host.sides(task))
        if tuple(orders) != sides:
            raise TrialError(
                f"{task} is played by the sides {', '.join(sides) or 'none'}; the leg names"
                f" {', '.join(orders)}"
            )
        values = host.check(task, first.params)
    except (TrialError, InvalidRequest) as err:
        return TrialResult(Ending.error(str(err)), out, backend=backend.name)
    progress.enter(Stage.PREPARING, options.run.prepare)
    prepared: dict[str, Prepared] = {}
    unready: dict[str, str] = {}
    outcomes = await asyncio.gather(
        *(
            _prepare_team(
                side, o, backend=backend, host=host, work=work, cache=cache, options=options.run
            )
            for side, o in orders.items()
        )
    )
    for side, outcome in zip(sides, outcomes, strict=True):
        if isinstance(outcome, str):
            unready[side] = f"could not start: {outcome}"
        else:
            prepared[side] = outcome
    if unready:  # nothing is played, no record: no result either
        why = "; ".join(f"{side} {unready[side]}" for side in sides if side in unready)
        return TrialResult(
            Ending.error(f"the leg was not played: {why}"), out, backend=backend.name
        )
    setup = MatchSetup(
        task=task,
        values=values,
        seed=first.seed,
        runtime=backend.runtime_digest(),
        teams={
            side: Team(
                p.code,
                p.config.in_manifest(
                    requirements_sha256=p.requirements_sha,
                    node_packages_sha256=p.node_packages_sha,
                ),
            )
            for side, p in prepared.items()
        },
    )
    try:
        lab = host.open_match(setup, out=out)
    except TrialError as err:
        return TrialResult(Ending.error(str(err)), out, backend=backend.name)
    progress.enter(Stage.RUNNING, options.run.run_deadline)
    return await _Leg(lab, prepared, backend=backend, options=options, work=work, out=out).run()


async def _prepare_team(
    side: str,
    order: Order,
    *,
    backend: Backend,
    host: TrialHost,
    work: Path,
    cache: Path,
    options: RunOptions,
) -> Prepared | str:
    """The side's team ready to start, or why it cannot be."""
    folder = work / side
    folder.mkdir()
    folder.chmod(0o755)
    try:
        p = await asyncio.wait_for(
            prepare(
                order,
                blind=False,
                backend=backend,
                host=host,
                work=folder,
                cache=cache,
                options=options,
                archive=None,
            ),
            options.prepare,
        )
    except TimeoutError:
        return f"preparing it took longer than {options.prepare:g} s"
    except (TrialError, SandboxError) as err:
        return str(err)
    config = p.config
    for said, why in (
        (config.realtime, "realtime = true: a match's teams step in lockstep"),
        (config.interface_files, "interfaces of its own: a match's teams use the lab's"),
        (config.data is not None, "[data]: a match's teams learn from no records"),
    ):
        if said:
            return str(ControllerConfigError(f"lab.toml has {why}"))
    return p


class _Leg:
    """The parts of one leg being played, and their orderly end."""

    def __init__(
        self,
        lab: MatchLab,
        prepared: Mapping[str, Prepared],
        *,
        backend: Backend,
        options: LegOptions,
        work: Path,
        out: Path,
    ) -> None:
        self.lab = lab
        self.prepared = prepared
        self.backend = backend
        self.options = options
        self.work = work
        self.out = out
        self.running: dict[str, Running] = {}
        self.exits: dict[str, Exit] = {}
        self.launched: float | None = None

    async def run(self) -> TrialResult:
        lab = self.lab
        manifest = lab.manifest
        sockets = {}
        for side in self.prepared:
            folder = self.work / side / "bridge"
            folder.mkdir()
            folder.chmod(0o755)
            sockets[side] = folder / "bridge.sock"
        ending = Ending.error("the leg did not start")
        result: dict[str, Value] = {}
        try:
            await lab.start(sockets)
            for socket in sockets.values():
                socket.chmod(0o777)
            self.launched = asyncio.get_running_loop().time()
            ending, result = await self._play(sockets)
        except asyncio.CancelledError:
            ending = Ending.cancelled("the leg was cancelled")
            await self._stop_all()
            raise
        except (TrialError, SandboxError) as err:
            ending = Ending.error(str(err))
            await self._stop_all()
        finally:
            leg = TrialResult(
                ending,
                self.out,
                manifest,
                manifest.digest,
                metrics={**lab.metrics(), **result},
                backend=self.backend.name,
            )
            now = asyncio.get_running_loop().time()
            first = lab.first_tick_at
            if self.launched is not None and first is not None:
                leg.start_seconds = round(first - self.launched, 4)
                leg.run_seconds = round(now - first, 4)
            failed = None
            try:
                leg.data_digest = await lab.finish(self._attachments(manifest, leg))
                leg.digest_topics = sorted(lab.digest_topics)
            except TrialError as err:
                failed = str(err)
            try:
                self._write_files(manifest)
            except OSError as err:
                failed = failed or storage_failure(err, "the leg's files could not be written")
            if failed is not None:
                log.error("leg in %s: %s", self.out, failed)
                leg.ending = Ending.lab_error(failed)
        return leg

    async def _play(self, sockets: Mapping[str, Path]) -> tuple[Ending, dict[str, Value]]:
        forfeits: dict[str, str] = {}
        starts = await asyncio.gather(
            *(self._start(side, socket) for side, socket in sockets.items()),
            return_exceptions=True,
        )
        for side, started in zip(sockets, starts, strict=True):
            if isinstance(started, SandboxError):
                forfeits[side] = f"could not start: {started}"
            elif isinstance(started, BaseException):
                raise started
        if not forfeits:
            forfeits = await self._watch()
        await self._stop_all()
        goals = {side: int(self.lab.metrics().get(f"{side}_goals", 0)) for side in sockets}
        return judge_leg(self.lab.episode(), goals, forfeits)

    async def _start(self, side: str, socket: Path) -> None:
        p = self.prepared[side]
        job = job_of(p, self.work / side / "code", socket, self.options.run.limits)
        self.running[side] = await self.backend.start(job)

    async def _watch(self) -> dict[str, str]:
        """Wait for the episode's end or the first side to fail; the sides that forfeit."""
        lab, options = self.lab, self.options
        loop = asyncio.get_running_loop()
        assert self.launched is not None
        exits = {
            asyncio.create_task(running.wait(), name=f"{side} exit"): side
            for side, running in self.running.items()
        }
        try:
            while True:
                episode = lab.episode()
                if not episode.running:
                    await self._grace(exits)
                    return {}
                limit = options.run.first_step if episode.tick == 0 else options.step_deadline
                last = lab.last_tick_at or self.launched
                quiet = loop.time() - last
                owing = lab.owing()
                if owing and quiet >= limit:
                    since = "its start" if episode.tick == 0 else f"tick {episode.tick}"
                    return {
                        side: f"sent no /lab/step within {limit:g} s of {since}" for side in owing
                    }
                waiter = asyncio.create_task(lab.ended())
                try:
                    done, _ = await asyncio.wait(
                        {*exits, waiter}, timeout=limit - quiet, return_when=asyncio.FIRST_COMPLETED
                    )
                finally:
                    waiter.cancel()
                    with contextlib.suppress(asyncio.CancelledError):
                        await waiter
                gone = [task for task in exits if task in done]
                if gone and lab.episode().running:
                    forfeits = {}
                    episode = lab.episode()
                    for task in gone:
                        side = exits[task]
                        exit_ = self.exits[side] = task.result()
                        forfeits[side] = judge(
                            exit_, episode, ended=False, limits=options.run.limits
                        ).reason.replace("the controller ", "its controller ")
                    return forfeits
        finally:
            for task, side in exits.items():
                if task.done() and not task.cancelled() and side not in self.exits:
                    self.exits[side] = task.result()
                task.cancel()

    async def _grace(self, exits: Mapping[asyncio.Task[Exit], str]) -> None:
        """The episode ended: every side gets ``grace`` to exit by itself."""
        waiting = [task for task in exits if not task.done()]
        if waiting:
            await asyncio.wait(waiting, timeout=self.options.run.grace)

    async def _stop_all(self) -> None:
        for side, running in self.running.items():
            if side not in self.exits:
                self.exits[side] = await running.stop()

    def _attachments(self, manifest: Manifest, leg: TrialResult) -> dict[str, tuple[str, bytes]]:
        files: dict[str, tuple[str, bytes]] = {
            **said_files(manifest, leg),
            **self.lab.model_files(),
        }
        for side, p in self.prepared.items():
            files[f"{side}.lab.toml"] = ("application/toml", p.config.text.encode())
            exit_ = self.exits.get(side)
            if exit_ is not None:
                names = side_logs(side)
                files[names["stdout"]] = ("text/plain", exit_.stdout)
                files[names["stderr"]] = ("text/plain", exit_.stderr)
        return files

    def _write_files(self, manifest: Manifest) -> None:
        for side, exit_ in self.exits.items():
            names = side_logs(side)
            write_whole(self.out / names["stdout"], exit_.stdout)
            write_whole(self.out / names["stderr"], exit_.stderr)
        write_whole(self.out / MANIFEST, readable_json(manifest.to_json()))
