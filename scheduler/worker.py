"""Workers: claim a trial, run it, file its record in the archive, repeat.

A worker holds its trial by a lease it renews every ``heartbeat`` seconds, while it
runs the trial and while it files it, but only while the trial moves: a trial stuck in
a stage past that stage's deadline is stopped and filed as an error, and if even that
hangs the heartbeat stops, the lease runs out and the queue treats the worker as dead.
When the queue says the trial must stop (its submitter cancelled it) the run is
cancelled and filed as cancelled. When the worker dies, the lease runs out and the
queue gives the trial to another worker: nothing is filed twice, because finishing is
conditional on still holding the lease.

Whatever goes wrong inside a trial (an exception anywhere in the runner, the lab side
or filing) ends that trial as an ``error`` with the reason, logged with its traceback,
and the worker goes on with the next one.

Filing a trial: the MCAP and the controller's logs go to the content-addressed store,
the record (manifest, digests, metrics, ending) to the index. A rerun is compared with
the trial it reruns: the same data digest is "reproduced", otherwise the first message
where the two records part says where they diverged. Once the trial is filed, the
record's summary for its page (``TrialHost.summarize``) is made within ``summary``
seconds and filed beside it as a derived artifact; a summary that fails is logged and
the trial stays filed without it (its page makes one when first asked).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

from repository.errors import ArchiveError
from repository.index import Derived
from repository.match import STEP_DEADLINE
from repository.trial import Claim, Ending, Filing, Kind, Status, Trial
from repository.well_known import (
    LOGS,
    RECORD_FILE,
    REPLAY,
    SUMMARY,
    SUMMARY_MEDIA_TYPE,
    side_logs,
)
from sandbox.api import Backend
from scheduler.canary import Canaries, Health
from scheduler.errors import FilingRefused, QueueError
from scheduler.host import TrialHost
from scheduler.leg import LegOptions, run_leg
from scheduler.outcome import storage_failure
from scheduler.runner import Progress, RunOptions, TrialResult, run_trial
from scheduler.states import Stage, State


class Jobs(Protocol):
    """Where a worker gets trials and files them: the queue itself (``Queue``, in
    ``labd serve``) or a lab's HTTP API (``scheduler.remote``, for ``labd worker``)."""

    def claim(self, worker: str) -> Claim | None: ...
    def heartbeat(self, trial_id: int, worker: str) -> bool: ...
    def finish(self, trial_id: int, worker: str, filing: Filing) -> bool: ...
    def trial(self, trial_id: int) -> Trial: ...
    def derive(self, trial_id: int, worker: str, item: Derived) -> bool: ...
    def report(self, health: Health) -> None: ...


class Blobs(Protocol):
    """Where records go: the blob store itself, or a lab's HTTP API."""

    def put_file(self, path: str | Path) -> str: ...
    def copy_to(self, digest: str, dest: str | Path) -> Path: ...


@dataclass
class WorkerConfig:
    name: str
    work: Path  # where trials run before they are filed
    cache: Path  # mirrors, runtimes, requirements
    heartbeat: float = 10.0  # seconds between lease renewals
    poll: float = 2.0  # seconds between claims while the queue is empty
    filing: float = 300.0  # seconds to store a record and file it
    summary: float = 120.0  # seconds to summarize a filed record for its page (0: none)
    replay: float = 600.0  # seconds to replay a filed record (0: no replay)
    canaries: tuple[int, ...] = ()  # reference trials to rerun at start and every ...
    canary_every: float = 3600.0  # ... seconds; one that diverges takes the worker out
    options: RunOptions = field(default_factory=RunOptions)


@dataclass(frozen=True)
class Current:
    """What a worker is doing: its trial, the stage, how long it has been at it."""

    trial: int
    attempt: int
    stage: Stage
    stage_seconds: float
    progress: Progress


class Worker:
    """Runs trials from ``queue`` one at a time until ``stop`` is set."""

    def __init__(
        self,
        queue: Jobs,
        store: Blobs,
        backend: Backend,
        host: TrialHost,
        config: WorkerConfig,
    ) -> None:
        self.queue = queue
        self.store = store
        self.backend = backend
        self.host = host
        self.config = config
        self.wake = asyncio.Event()  # set by a submission, to claim at once
        self.log = logging.getLogger(f"scheduler.worker.{config.name}")
        self._current: tuple[Claim, Progress] | None = None
        self._deriving: asyncio.Task[None] | None = None  # the last filed record's summary, replay
        self.canaries = Canaries(config.canaries, config.canary_every)
        self.health = Health(config.name, State.OK, "no canaries" if not config.canaries else "")

    @property
    def current(self) -> Current | None:
        if self._current is None:
            return None
        claim, progress = self._current
        return Current(claim.id, claim.attempt, progress.stage, progress.elapsed, progress)

    async def run(self, stop: asyncio.Event) -> None:
        stopping = asyncio.create_task(stop.wait())
        try:
            while not stop.is_set():
                if self.canaries.due():
                    await self._check_canaries()
                if self.health.state is State.OUT:  # out of the pool: claim nothing, until stopped
                    await asyncio.wait({stopping}, timeout=self.config.poll)
                    continue
                try:
                    claim = await asyncio.to_thread(self.queue.claim, self.config.name)
                except QueueError as err:  # a remote lab that is down: try again later
                    self.log.warning("could not claim a trial: %s", err)
                    claim = None
                if claim is None:
                    self.wake.clear()
                    waker = asyncio.create_task(self.wake.wait())
                    try:
                        await asyncio.wait(
                            {waker, stopping},
                            timeout=self.config.poll,
                            return_when=asyncio.FIRST_COMPLETED,
                        )
                    finally:
                        waker.cancel()
                        with contextlib.suppress(asyncio.CancelledError):
                            await waker
                    continue
                try:
                    await self.execute(claim)
                except Exception:  # a bug: never let one trial stop the worker
                    self.log.exception("trial %d: the worker failed; going on", claim.id)
        finally:
            stopping.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await stopping
            if self._deriving is not None:
                await _stopped(self._deriving)

    async def _check_canaries(self) -> None:
        self.health = Health(self.config.name, State.CHECKING, "rerunning the canaries")
        await self._report()
        try:
            self.health = await self.canaries.check(self)
        except Exception as err:  # a bug: say so in the status, claim nothing meanwhile
            self.log.exception("the canaries could not be checked")
            self.health = Health(self.config.name, State.OUT, f"the canaries could not run: {err}")
        await self._report()

    async def _report(self) -> None:
        try:
            await asyncio.to_thread(self.queue.report, self.health)
        except QueueError as err:
            self.log.warning("could not report the worker's health: %s", err)

    async def execute(self, claim: Claim) -> None:
        """Run one claimed trial to its end and file it."""
        out = self.config.work / f"trial-{claim.id}-{claim.attempt}"
        shutil.rmtree(out, ignore_errors=True)
        order = claim.order
        self.log.info("trial %d: %s@%s %s", claim.id, order.repository, order.commit[:12], order)
        progress = Progress()
        self._current = (claim, progress)
        running = asyncio.create_task(self._run(claim, out, progress))
        stuck: list[str] = []
        beat = asyncio.create_task(self._heartbeat(claim.id, running, progress, stuck))
        result: TrialResult | None = None
        ending: Ending | None = None
        try:
            result = await running
        except asyncio.CancelledError:
            me = asyncio.current_task()
            if me is not None and me.cancelling():
                await _stopped(beat)
                raise  # the worker itself is being stopped: the lease will requeue the trial
            ending = Ending.error(stuck[0]) if stuck else Ending.cancelled("cancelled while it ran")
        except Exception as err:
            self.log.exception("trial %d: the lab failed while running it", claim.id)
            ending = Ending.lab_error(
                f"the lab failed while running the trial ({_name(err)}: {err})"
            )
        except BaseException:
            await _stopped(beat)
            raise
        # The lease is renewed while filing too (a big record to a slow store may take
        # longer than a lease), until the filing deadline.
        try:
            progress.enter(Stage.FILING, self.config.filing)
            filing = await asyncio.wait_for(
                asyncio.to_thread(self._filing, claim, result, ending, out), self.config.filing
            )
        except TimeoutError:
            filing = Filing.error(
                f"the archive did not store the record within {self.config.filing:g} s"
            )
        except Exception as err:
            self.log.exception("trial %d: the record could not be filed", claim.id)
            filing = Filing.error(f"the lab could not file the record ({_name(err)})")
        finally:
            await _stopped(beat)
        await self._file(claim, filing, out)

    async def _run(self, claim: Claim, out: Path, progress: Progress) -> TrialResult:
        """Run the claimed trial, or play the claimed leg of a match."""
        order = claim.order
        if order.away is None:
            return await run_trial(
                order,
                blind=claim.blind,
                backend=self.backend,
                host=self.host,
                out=out,
                cache=self.config.cache,
                options=self.config.options,
                progress=progress,
                archive=self.store,  # the records the trial learns from
            )
        assert order.task is not None  # the queue holds its orders resolved
        home, away = self.host.sides(order.task)[:2]
        team = {"kind": Kind.TRIAL, "away": None, "step_deadline": None}
        orders = {
            home: order.model_copy(update=team),
            away: order.model_copy(update={**team, **order.away.model_dump(), "ref": None}),
        }
        return await run_leg(
            orders,
            backend=self.backend,
            host=self.host,
            out=out,
            cache=self.config.cache,
            options=LegOptions(
                run=self.config.options, step_deadline=order.step_deadline or STEP_DEADLINE
            ),
            progress=progress,
        )

    async def _file(self, claim: Claim, filing: Filing, out: Path) -> None:
        """File the trial; then what is made of its record is made beside the next trial."""
        kept = False  # the folder goes to what is made of the record, which removes it
        try:
            filed, filing = await asyncio.to_thread(self._finish, claim.id, filing)
            self.log.info(
                "trial %d %s: %s",
                claim.id,
                filing.outcome or filing.status,
                filing.reason,
            )
            if filed and filing.mcap:
                await self.settled()  # one record worked on at a time, beside the next trial
                self._deriving = asyncio.create_task(
                    self._derive(claim.id, out), name=f"{self.config.name}: trial {claim.id}"
                )
                kept = True
        except QueueError as err:  # the lease will run out and the trial run again
            self.log.error("trial %d could not be filed: %s", claim.id, err)
        finally:
            self._current = None
            if not kept:
                shutil.rmtree(out, ignore_errors=True)

    async def settled(self) -> None:
        """Wait until what is made of the last filed record (its summary, its replay's
        verdict) is filed. The worker goes on to its next trial meanwhile: that work runs
        in helper processes, on a core the next trial leaves free."""
        task = self._deriving
        if task is not None and not task.done():
            # (not ``await task``: its failure or cancellation is its own, never the
            # worker's; ``wait`` raises only if the worker itself is cancelled)
            await asyncio.wait({task})

    def _finish(self, trial_id: int, filing: Filing) -> tuple[bool, Filing]:
        """File the trial; a filing the lab refuses (its record does not bear it out: a
        bug of this worker's, or another lab version's) is filed again as an error saying
        why, without the record. Whether it was filed, and what was."""
        try:
            return self.queue.finish(trial_id, self.config.name, filing), filing
        except FilingRefused as err:
            self.log.error("trial %d: %s", trial_id, err)
            problems = "; ".join(err.problems)
            refused = Filing.error(f"the lab refused the worker's record of the trial: {problems}")
            return self.queue.finish(trial_id, self.config.name, refused), refused

    async def _heartbeat(
        self,
        trial_id: int,
        running: asyncio.Task[TrialResult],
        progress: Progress,
        stuck: list[str],
    ) -> None:
        while True:
            await asyncio.sleep(self.config.heartbeat)
            late = progress.overdue()
            if late > 0:
                reason = (
                    f"the trial made no progress: it was {progress.stage} for"
                    f" {progress.elapsed:.0f} s, past that stage's deadline"
                )
                self.log.error("trial %d: %s; stopping it", trial_id, reason)
                stuck.append(reason)
                running.cancel()
                return  # no more renewals: if stopping hangs too, the lease runs out
            # a renewal that gets no answer must not hold up the progress check above
            wait = max(3 * self.config.heartbeat, 5.0)
            renewal = asyncio.ensure_future(
                asyncio.to_thread(self.queue.heartbeat, trial_id, self.config.name)
            )
            # (``wait``, not ``wait_for``: on Python 3.11 a ``wait_for`` whose inner call
            # ends as the task is cancelled returns its result and drops the cancel, and
            # this loop would renew the lease of a filed trial for ever)
            done, _ = await asyncio.wait({renewal}, timeout=wait)
            if not done:
                self.log.warning("trial %d: heartbeat had no answer within %g s", trial_id, wait)
                continue
            try:
                keep = renewal.result()
            except QueueError as err:  # a remote lab briefly away: the lease may still hold
                self.log.warning("trial %d: heartbeat failed: %s", trial_id, err)
                continue
            if not keep:
                self.log.info("trial %d: stopping (cancelled, or the lease was lost)", trial_id)
                running.cancel()
                return

    def _filing(
        self, claim: Claim, result: TrialResult | None, ending: Ending | None, out: Path
    ) -> Filing:
        """What to file for a trial that ended; its files go to the blob store."""
        record: dict[str, Any]
        if result is None:
            assert ending is not None
            record = ending.model_dump()
        else:
            record = {
                **result.ending.model_dump(),
                "manifest": result.manifest.to_json() if result.manifest else None,
                "manifest_digest": result.manifest_digest or None,
                "data_digest": result.data_digest or None,
                "digest_topics": result.digest_topics or None,
                "metrics": result.metrics or None,
                "backend": result.backend,
                "wall_seconds": round(result.wall_seconds, 3),
            }
        try:
            # Only a run that returned made whole files (the runner deletes a record it
            # could not finish); after an exception, what is in ``out`` may be partial.
            mcap = out / RECORD_FILE
            if result is not None and mcap.exists():
                record["mcap"] = self.store.put_file(mcap)
                record["mcap_size"] = mcap.stat().st_size
            else:  # no record to bear them out: the lab refuses digests and metrics alone
                for name in ("data_digest", "digest_topics", "metrics"):
                    record.pop(name, None)
            logs = LOGS
            if claim.order.away is not None and claim.order.task is not None:
                logs = side_logs(self.host.sides(claim.order.task)[0])  # home's
            for stream, name in logs.items():
                path = out / name
                if result is not None and path.exists():
                    record[stream] = self.store.put_file(path)
        except OSError as err:
            self.log.exception("trial %d: the record could not be stored", claim.id)
            return Filing.lab_error(storage_failure(err, "the archive could not store the record"))
        except (ArchiveError, QueueError) as err:
            self.log.exception("trial %d: the record could not be stored", claim.id)
            return Filing.lab_error(f"the archive could not store the trial's record: {err}")
        rerun_of = claim.order.rerun_of
        if rerun_of is not None and result is not None and result.status is Status.FINISHED:
            record.update(self._compare(rerun_of, result))
        return Filing(**record)

    async def _summarize(self, trial_id: int, mcap: Path) -> None:
        """File the record's page summary beside it; never fails the filed trial."""
        seconds = self.config.summary
        if seconds <= 0:
            return
        try:
            blob = await asyncio.wait_for(
                asyncio.to_thread(self.host.summarize, mcap, seconds=seconds), seconds + 1
            )
            if blob is None:
                return
            path = mcap.with_name(SUMMARY)
            path.write_bytes(blob)
            digest = await asyncio.to_thread(self.store.put_file, path)
            item = Derived(SUMMARY, digest, len(blob), SUMMARY_MEDIA_TYPE)
            await asyncio.to_thread(self.queue.derive, trial_id, self.config.name, item)
        except TimeoutError:
            self.log.error(
                "trial %d: its summary took longer than %g s; none filed", trial_id, seconds
            )
        except Exception:  # whatever it was, the trial is filed: its page makes one later
            self.log.exception("trial %d: its summary could not be filed", trial_id)

    async def _derive(self, trial_id: int, out: Path) -> None:
        """What is made of a filed record, beside it: its page summary, its replay's
        verdict; then the trial's folder is removed. (Its video is the service's to
        render, when asked or when the machine is idle: ``labd.videos``.)"""
        try:
            await self._summarize(trial_id, out / RECORD_FILE)
            await self._replay(trial_id, out / RECORD_FILE)
        finally:
            # removed even when the worker stops meanwhile (it cancels this task): a
            # cancelled wait on the thread would leave the folder half removed, or whole
            removal = asyncio.ensure_future(asyncio.to_thread(shutil.rmtree, out, True))
            try:
                await asyncio.shield(removal)
            except asyncio.CancelledError:
                await removal
                raise

    async def _replay(self, trial_id: int, mcap: Path) -> None:
        """Replay the filed record and file the verdict beside it; never fails the filed
        trial (a replay that diverges is its verdict)."""
        seconds = self.config.replay
        if seconds <= 0:
            return
        folder = mcap.with_name("replay")
        try:
            done = await asyncio.wait_for(
                asyncio.to_thread(self.host.replay, mcap, folder, seconds=seconds), seconds + 1
            )
            if done is None:
                return
            if not done.verified:
                self.log.warning("trial %d: %s", trial_id, json.loads(done.verdict)["said"])
            folder.mkdir(exist_ok=True)
            path = folder / REPLAY
            path.write_bytes(done.verdict)
            digest = await asyncio.to_thread(self.store.put_file, path)
            verdict = Derived(REPLAY, digest, len(done.verdict), "application/json")
            await asyncio.to_thread(self.queue.derive, trial_id, self.config.name, verdict)
        except TimeoutError:
            self.log.error(
                "trial %d: its replay took longer than %g s; none filed", trial_id, seconds
            )
        except Exception:  # whatever it was, the trial is filed; its page says "not replayed"
            self.log.exception("trial %d: its replay could not be filed", trial_id)

    def _compare(self, original_id: int, result: TrialResult) -> dict[str, Any]:
        """Did this rerun reproduce the trial it reruns?"""
        original = self.queue.trial(original_id)
        if not original.data_digest or not original.mcap:
            return {"reproduced": None, "divergence": "the original trial has no record"}
        if not result.data_digest or result.mcap is None:
            return {"reproduced": False, "divergence": "the rerun made no record"}
        if original.data_digest == result.data_digest:
            return {"reproduced": True, "divergence": None}
        topics = original.digest_topics or result.digest_topics
        with tempfile.TemporaryDirectory(prefix="labd-compare-") as folder:
            theirs = Path(folder) / "original.mcap"
            try:
                self.store.copy_to(original.mcap, theirs)
            except (ArchiveError, QueueError) as err:
                return {"reproduced": False, "divergence": f"the original's record: {err}"}
            difference = self.host.first_difference(theirs, result.mcap, topics)
        text = difference or "the data digests differ"
        ran = result.manifest.to_json() if result.manifest else {}
        changed = manifest_changes(original.manifest or {}, ran)
        if changed:
            text += f"; the manifest differs in {', '.join(changed)}"
        return {"reproduced": False, "divergence": text}


def manifest_changes(a: dict[str, Any], b: dict[str, Any], prefix: str = "") -> list[str]:
    """The dotted keys whose values differ between two manifests."""
    changed = []
    for key in sorted(set(a) | set(b)):
        x, y = a.get(key), b.get(key)
        if isinstance(x, dict) and isinstance(y, dict):
            changed += manifest_changes(x, y, f"{prefix}{key}.")
        elif x != y:
            changed.append(prefix + key)
    return changed


async def _stopped(task: asyncio.Task[None]) -> None:
    """Cancel ``task`` and wait for its end; cancelled again should a cancel be lost (a
    ``wait_for`` inside it may drop one on Python 3.11)."""
    while not task.done():
        task.cancel()
        await asyncio.wait({task}, timeout=1.0)
    if not task.cancelled() and task.exception() is not None:
        logging.getLogger("scheduler.worker").error(
            "%s failed", task.get_name(), exc_info=task.exception()
        )


def _name(err: BaseException) -> str:
    return type(err).__name__
