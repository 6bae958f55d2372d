"""The lab's trials on a Ray cluster (``labd serve --ray-address ADDRESS``).

The queue stays the truth: submissions, fair share, quotas, cancels and leases are the
index's, as for every worker. A dispatcher here claims runnable trials with the queue's
own conditional claim, never more at once than the cluster has slots (its nodes'
``labd_sim`` resource: an operator gives each node as many as it should run trials),
and runs each as one Ray task:

    Queue.claim ─▶ a Ray task on some node ─▶ Worker.execute there (fetch the pinned
    commit, build, sandbox with no network, lockstep, record; the record and logs go to
    the lab's blob store, content-addressed) ─▶ what a worker files, handed back
    ─▶ Queue.finish by ray:NODE (held to its record, signed)
    ─▶ its slot is free ─▶ the record's page summary, made by the node's helper

While a task runs, the dispatcher renews the trial's lease; a cancelled trial has its
task cancelled. A task whose node dies is run again elsewhere by Ray (``max_retries``)
and filed once, since only the dispatcher files, and a retried task rewrites the same
blob keys; a controller's own crash is an outcome, never retried. Should the lab itself
stop, its tasks stop with it (they are its driver's) and the leases run out: the queue
gives the trials to the next dispatcher.

The untrusted controller runs in the node's sandbox inside the task, as on a worker,
never as Ray code. The records a trial learns from, and the records it makes, travel
through the lab's blob store, so every node must reach it (an S3 bucket, or a folder
every node mounts at the same path).

Each record a node filed is replayed (``labd.replays``) by a task of its own, placed on
another node than the one that ran the trial when the cluster has one, and the verdict
says where (``node``). Summaries and replays hold no slot: each node has a helper (a Ray
actor asking for no CPU, ``NodeHelper``) that makes them in helper processes it keeps
warm, beside the node's next trial, as a worker's helpers do; the lab keeps as many
replays under way as the cluster has slots. A helper whose node dies is made again on
another node, and what it was doing is asked of that one.

Ray is imported only here, and only when a cluster is asked for (``pip install
'labd[cluster]'``).
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import json
import logging
import os
import shutil
import socket
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import sandbox
from labd.errors import LabError
from labd.trial import LabHost, client_library
from repository.blobs import BlobStore
from repository.index import Derived
from repository.trial import Claim, Ending, Filing, Trial
from repository.well_known import RECORD_FILE, SUMMARY, SUMMARY_MEDIA_TYPE
from scheduler.canary import Health
from scheduler.errors import FilingRefused, QueueError
from scheduler.queue import Queue
from scheduler.runner import RunOptions
from scheduler.worker import Worker, WorkerConfig

log = logging.getLogger("labd.cluster")
RESOURCE = "labd_sim"  # a node's slots for trials and replays
PREFIX = "ray:"  # a trial's worker when a node of the cluster ran it: ray:NODE
NODE_ID = 12  # hex digits of Ray's node id that name a node


class ClusterError(LabError):
    """The cluster cannot be used: Ray is not installed, or does not answer."""


@dataclass(frozen=True)
class NodeSetup:
    """What a node needs to run a trial as the lab's workers do (sent with each task)."""

    blobs: str  # the lab's blob store: a folder every node mounts, or an fsspec URL
    blob_options: dict[str, Any]
    work: Path  # where the node runs trials (made if missing)
    cache: Path  # the node's mirrors, runtimes and requirements
    sandbox: str | None
    options: RunOptions
    heartbeat: float = 10.0


@dataclass(frozen=True)
class ClusterConfig:
    address: str  # as ray.init takes it: HOST:PORT, ray://HOST:PORT, or "auto"
    resource: str = RESOURCE
    max_retries: int = 3  # runs of a task whose node died, before the trial is an error
    poll: float = 2.0  # seconds between claims while the queue is empty or the cluster full
    replay: float = 1800.0  # one replay's limit, in seconds
    summary: float = 120.0  # one record's page summary's limit, in seconds


def node_name(node_id: str) -> str:
    """The worker name of the node ``node_id`` (Ray's hex id)."""
    return PREFIX + node_id[:NODE_ID]


# -- on a node ----------------------------------------------------------------------------


class _OneClaim:
    """The queue as a node's worker sees it for its one trial: its lease is the
    dispatcher's to renew, and what it files is kept to hand back (``Jobs``)."""

    def __init__(self, original: Trial | None) -> None:
        self.original = original
        self.filing: Filing | None = None
        self.derived: list[Derived] = []

    def claim(self, worker: str) -> Claim | None:
        return None

    def heartbeat(self, trial_id: int, worker: str) -> bool:
        return True  # the dispatcher holds the lease; a cancel cancels this task

    def finish(self, trial_id: int, worker: str, filing: Filing) -> bool:
        self.filing = filing
        return True

    def trial(self, trial_id: int) -> Trial:
        if self.original is None or self.original.id != trial_id:
            raise QueueError(f"trial {trial_id} is not the one this trial reruns")
        return self.original

    def derive(self, trial_id: int, worker: str, item: Derived) -> bool:
        self.derived.append(item)
        return True

    def report(self, health: Health) -> None:
        return None


_backends: dict[tuple[str | None, Path], Any] = {}  # one per Ray worker process


def _backend(setup: NodeSetup) -> Any:
    key = (setup.sandbox, setup.cache)
    if key not in _backends:
        _backends[key] = sandbox.backend(setup.sandbox, setup.cache, [client_library()])
    return _backends[key]


@functools.cache
def _host() -> LabHost:
    """The process's host (one: it reads the message types once)."""
    return LabHost()


def _this_node() -> str:
    import ray  # noqa: PLC0415 (only where a cluster runs)

    return node_name(ray.get_runtime_context().get_node_id())


def run_on_node(claim_json: str, original_json: str | None, setup: NodeSetup) -> dict[str, Any]:
    """A Ray task's body: run the claimed trial as a worker does, on this node, with the
    record and logs put in the lab's store; what to file, which node ran it, and when
    the task began (by the node's clock)."""
    began = time.time()
    claim = Claim.model_validate_json(claim_json)
    original = Trial.model_validate_json(original_json) if original_json else None
    name = _this_node()
    setup = _here(setup)
    setup.work.mkdir(parents=True, exist_ok=True)
    held = _OneClaim(original)
    worker = Worker(
        held,
        BlobStore(setup.blobs, setup.blob_options or None),
        _backend(setup),
        _host(),
        WorkerConfig(
            name=name,
            work=setup.work,
            cache=setup.cache,
            heartbeat=setup.heartbeat,
            summary=0.0,  # made once the trial is filed and its slot free (``NodeHelper``)
            replay=0.0,  # replayed by another task, on another node (``replay_on_node``)
            options=setup.options,
        ),
    )

    async def run() -> None:
        await worker.execute(claim)
        await worker.settled()  # the trial's folder removed

    asyncio.run(run())
    if held.filing is None:  # execute always files; a bug otherwise
        raise RuntimeError(f"trial {claim.id}: the node's worker filed nothing")
    return {
        "node": name,
        "began": began,
        "filing": held.filing.model_dump(mode="json"),
        "derived": [vars(item) for item in held.derived],
    }


def _here(setup: NodeSetup) -> NodeSetup:
    """The setup as this node runs it: its own cache where it says one (``LABD_CACHE``
    in its environment: a runtime built into its image), else the lab's path."""
    own = os.environ.get("LABD_CACHE")
    return replace(setup, cache=Path(own)) if own else setup


def summarize_on_node(mcap: str, setup: NodeSetup, seconds: float) -> dict[str, Any]:
    """The page summary of the record ``mcap`` (a digest in the lab's
    store), put in the store; what to file beside the trial (``Derived``'s fields)."""
    store = BlobStore(setup.blobs, setup.blob_options or None)
    setup.work.mkdir(parents=True, exist_ok=True)
    folder = Path(tempfile.mkdtemp(prefix="summary-", dir=setup.work))
    try:
        record = store.copy_to(mcap, folder / RECORD_FILE)
        blob = _host().summarize(record, seconds=seconds)
        path = folder / SUMMARY
        path.write_bytes(blob)
        return vars(Derived(SUMMARY, store.put_file(path), len(blob), SUMMARY_MEDIA_TYPE))
    finally:
        shutil.rmtree(folder, ignore_errors=True)


def replay_on_node(mcap: str, setup: NodeSetup, seconds: float) -> dict[str, Any]:
    """Replay the record ``mcap`` (a digest in the lab's store) on
    this node; the verdict (JSON bytes) with ``node`` added."""
    store = BlobStore(setup.blobs, setup.blob_options or None)
    setup.work.mkdir(parents=True, exist_ok=True)
    folder = Path(tempfile.mkdtemp(prefix="replay-", dir=setup.work))
    try:
        record = store.copy_to(mcap, folder / RECORD_FILE)
        done = _host().replay(record, folder / "replay", seconds=seconds)
        verdict = {**json.loads(done.verdict), "node": _this_node()}
        return {"verdict": json.dumps(verdict, indent=2, sort_keys=True).encode()}
    finally:
        shutil.rmtree(folder, ignore_errors=True)


class NodeHelper:
    """A Ray actor on one node, for as long as the lab is joined: it makes the page
    summaries and replays of filed records there, several at once, in the helper
    processes of its own process (``labd.offload``), which stay warm between records.
    It asks for no CPU and no slot: its work runs beside the node's trials."""

    def summarize(self, mcap: str, setup: NodeSetup, seconds: float) -> dict[str, Any]:
        return summarize_on_node(mcap, setup, seconds)

    def replay(self, mcap: str, setup: NodeSetup, seconds: float) -> dict[str, Any]:
        return replay_on_node(mcap, setup, seconds)


HELPER_CALLS = 4  # a helper's calls under way at once (its helper processes share them)
LOST = 60.0  # seconds a node whose helper died is not asked again (Ray may not know yet)


# -- in the lab ---------------------------------------------------------------------------


@dataclass
class Slots:
    """What the cluster has for the lab: its nodes with the resource, and its slots."""

    nodes: int = 0
    total: int = 0
    free: int = 0
    in_flight: int = 0  # the lab's trials running there now (each holding a slot)


@dataclass
class _Running:
    claim: Claim
    name: str  # the worker name the lease is held under until a node is known
    task: asyncio.Task[None] = field(repr=False)
    holds_slot: bool = True  # until the trial is filed (its summary is made on no slot)


class Cluster:
    """Claims trials from ``queue`` and runs them on the Ray cluster at ``config.address``."""

    def __init__(self, queue: Queue, config: ClusterConfig, node: NodeSetup, *, name: str) -> None:
        self.queue = queue
        self.config = config
        self.node = node  # sent with each task (the lab changes it once it serves)
        self.name = name  # the lab's: leases are held as NAME/ray until a node is known
        self.wake = asyncio.Event()
        self.slots = Slots()
        self._running: dict[int, _Running] = {}
        self._ray: Any = None
        self._trial_task: Any = None
        self._helper_class: Any = None
        self._helpers: dict[str, Any] = {}  # node id -> its NodeHelper
        self._lost: dict[str, float] = {}  # nodes whose helper died -> when (not asked a while)

    # -- connecting ------------------------------------------------------------------

    def connect(self) -> None:
        """Join the cluster (``ClusterError`` naming what is missing)."""
        try:
            import ray  # noqa: PLC0415 (the extra's)
        except ImportError:
            raise ClusterError("--ray-address needs Ray: pip install 'labd[cluster]'") from None
        _probe(self.config.address)
        try:
            ray.init(
                address=self.config.address,
                namespace="labd",
                log_to_driver=False,
                ignore_reinit_error=True,
                configure_logging=False,
            )
        except (ConnectionError, RuntimeError, ValueError, TimeoutError) as err:
            raise ClusterError(f"no Ray cluster answers at {self.config.address}: {err}") from None
        self._ray = ray
        resources = {self.config.resource: 1}
        self._trial_task = ray.remote(run_on_node).options(
            num_cpus=1,
            resources=resources,
            max_retries=self.config.max_retries,
            retry_exceptions=False,
            name="labd trial",
        )
        self._helper_class = ray.remote(NodeHelper)
        self.refresh()
        log.info(
            "Ray cluster at %s: %d node(s), %d slot(s) of %s",
            self.config.address,
            self.slots.nodes,
            self.slots.total,
            self.config.resource,
        )

    @property
    def connected(self) -> bool:
        return self._ray is not None

    def close(self) -> None:
        if self._ray is not None:
            self._helpers.clear()
            self._ray.shutdown()
            self._ray = None

    def nodes(self) -> dict[str, str]:
        """The live nodes that have the resource: worker name -> Ray's node id."""
        assert self._ray is not None
        return {
            node_name(node["NodeID"]): node["NodeID"]
            for node in self._ray.nodes()
            if node["Alive"] and node["Resources"].get(self.config.resource, 0) > 0
        }

    def refresh(self) -> Slots:
        """Count the cluster's nodes and slots now (for claims, /readyz and /metrics)."""
        assert self._ray is not None
        total = self._ray.cluster_resources().get(self.config.resource, 0)
        free = self._ray.available_resources().get(self.config.resource, 0)
        self.slots = Slots(len(self.nodes()), int(total), int(free), self._holding())
        return self.slots

    def _holding(self) -> int:
        """The lab's trials holding a slot of the cluster now."""
        return sum(running.holds_slot for running in self._running.values())

    @property
    def parallel(self) -> int:
        """Replays of what the nodes ran at once: as many as the cluster has slots."""
        return max(1, self.slots.total)

    # -- dispatching -------------------------------------------------------------------

    async def run(self, stop: asyncio.Event) -> None:
        """Claim and dispatch trials until ``stop`` is set; then cancel what runs."""
        stopping = asyncio.create_task(stop.wait())
        try:
            while not stop.is_set():
                claimed = False
                try:
                    slots = await asyncio.to_thread(self.refresh)
                    if self._holding() < slots.total:
                        claimed = await self._claim_one()
                except Exception:  # the cluster or the database away for a moment
                    log.exception("could not dispatch a trial to the cluster")
                if claimed:
                    continue
                self.wake.clear()
                waker = asyncio.create_task(self.wake.wait())
                await asyncio.wait(
                    {waker, stopping}, timeout=self.config.poll, return_when=asyncio.FIRST_COMPLETED
                )
                waker.cancel()
        finally:
            stopping.cancel()
            for running in list(self._running.values()):
                running.task.cancel()
            for running in list(self._running.values()):
                with contextlib.suppress(asyncio.CancelledError, Exception):
                    await running.task

    async def _claim_one(self) -> bool:
        name = f"{self.name}/ray"
        claim = await asyncio.to_thread(self.queue.claim, name)
        if claim is None:
            return False
        task = asyncio.create_task(self._dispatch(claim, name), name=f"ray trial {claim.id}")
        self._running[claim.id] = _Running(claim, name, task)
        task.add_done_callback(lambda _: self._freed(claim.id))
        return True

    def _freed(self, trial_id: int) -> None:
        """A trial's task ended: its slot is free, so claim the next trial now rather than
        at the next poll."""
        self._running.pop(trial_id, None)
        self.wake.set()

    async def _dispatch(self, claim: Claim, name: str) -> None:
        """Run one claimed trial on the cluster and file it."""
        rerun_of = claim.order.rerun_of
        original = None
        if rerun_of is not None:
            original = (await asyncio.to_thread(self.queue.trial, rerun_of)).model_dump_json()
        sent = time.time()
        ref = self._trial_task.remote(claim.model_dump_json(), original, self.node)
        log.info("trial %d: sent to the cluster", claim.id)
        outcome: dict[str, Any] | None = None
        filing: Filing | None = None
        try:
            outcome = await self._held(claim.id, name, ref)
        except _Stop as stop:
            self._ray.cancel(ref, force=True)
            filing = Filing(**Ending.cancelled(stop.reason).model_dump())
        except asyncio.CancelledError:  # the lab stops: the lease will requeue the trial
            self._ray.cancel(ref, force=True)
            raise
        except self._ray.exceptions.RayError as err:  # failed past its retries: the lab's fault
            log.error("trial %d: the cluster lost it: %s", claim.id, err)
            reason = f"the cluster could not run the trial ({type(err).__name__}: {err})"
            filing = Filing.lab_error(reason[:500])
        ran_on = name  # the lab's, until a node is known
        if outcome is not None:
            ran_on = outcome["node"]
            log.info("trial %d: began on %s %.3f s after it was sent (by the two clocks)",
                     claim.id, ran_on, outcome["began"] - sent)  # fmt: skip
            filing = Filing.model_validate(outcome["filing"])
        assert filing is not None
        filed = await asyncio.to_thread(self._finish, claim.id, name, filing, ran_on)
        if (running := self._running.get(claim.id)) is not None:
            running.holds_slot = False  # claim the next trial while the summary is made
            self.wake.set()
        if filed and outcome is not None:
            for item in outcome["derived"]:
                await asyncio.to_thread(self.queue.derive, claim.id, ran_on, Derived(**item))
            if filing.mcap:
                await self._summarize(claim.id, ran_on, filing.mcap)

    async def _summarize(self, trial_id: int, node: str, mcap: str) -> None:
        """File the record's page summary, made on the node that ran the trial (or
        another, should it be gone); never fails the filed trial (its page makes one
        later)."""
        seconds = self.config.summary
        try:
            made = await asyncio.wait_for(
                self._on_a_node("summarize", lambda nodes: [nodes[node]] if node in nodes else [],
                                mcap, seconds),
                seconds + 30,
            )  # fmt: skip
            await asyncio.to_thread(self.queue.derive, trial_id, node, Derived(**made))
        except Exception as err:  # noqa: BLE001 (logged; the trial stays filed)
            said = str(err).splitlines()[0] if str(err) else type(err).__name__
            log.error("trial %d: its summary could not be made on the cluster: %s", trial_id, said)

    async def _on_a_node(
        self, call: str, preferred: Callable[[dict[str, str]], list[str]], mcap: str, seconds: float
    ) -> dict[str, Any]:
        """Ask a node's helper to ``call`` on the record ``mcap``: on the first of the
        ``preferred`` live nodes, else any; a helper whose node died is dropped and the
        next node asked, at most ``max_retries`` times."""
        for _ in range(self.config.max_retries + 1):
            live = await asyncio.to_thread(self.nodes)
            now = time.monotonic()  # a node Ray has let go of, or that came back, is forgotten
            self._lost = {n: t for n, t in self._lost.items() if n in live.values() and now < t}
            nodes = {name: node for name, node in live.items() if node not in self._lost}
            candidates = preferred(nodes) or list(nodes.values())
            if not candidates:
                raise ClusterError(f"no node of the cluster has {self.config.resource}")
            chosen = candidates[0]
            ref = getattr(self._helper(chosen), call).remote(mcap, self.node, seconds)
            try:
                done: dict[str, Any] = await asyncio.wrap_future(ref.future())
                return done
            except self._ray.exceptions.RayActorError as err:
                log.warning("the helper on node %s is gone (%s): asking another", chosen[:NODE_ID],
                            type(err).__name__)  # fmt: skip
                self._helpers.pop(chosen, None)
                self._lost[chosen] = time.monotonic() + LOST
        raise ClusterError(f"no node's helper could {call} the record")

    def _helper(self, node_id: str) -> Any:
        """The node's helper, made at its first use: on that node only."""
        if (helper := self._helpers.get(node_id)) is None:
            helper = self._helpers[node_id] = self._helper_class.options(
                num_cpus=0,
                max_concurrency=HELPER_CALLS,
                scheduling_strategy=_on(node_id),
            ).remote()
        return helper

    async def _held(self, trial_id: int, name: str, ref: Any) -> dict[str, Any]:
        """Wait for the task, renewing the trial's lease; ``_Stop`` if it must stop."""
        future = asyncio.wrap_future(ref.future())
        beat = self.node.heartbeat
        while True:
            done, _ = await asyncio.wait({future}, timeout=beat)
            if done:
                result: dict[str, Any] = future.result()
                return result
            try:
                keep = await asyncio.to_thread(self.queue.heartbeat, trial_id, name)
            except Exception:  # the database away for a moment: the lease may hold
                log.exception("trial %d: heartbeat failed", trial_id)
                continue
            if not keep:
                raise _Stop("cancelled while it ran")

    def _finish(self, trial_id: int, worker: str, filing: Filing, ran_on: str) -> bool:
        """File the trial ``worker`` holds, as run by ``ran_on``; one the lab refuses is
        filed as an error saying why."""
        try:
            filed = self.queue.finish(trial_id, worker, filing, ran_on=ran_on)
        except FilingRefused as err:
            log.error("trial %d: %s", trial_id, err)
            problems = "; ".join(err.problems)
            refused = Filing.error(f"the lab refused the node's record of the trial: {problems}")
            filed = self.queue.finish(trial_id, worker, refused, ran_on=ran_on)
        log.info("trial %d %s on %s: %s", trial_id, filing.outcome or filing.status, ran_on,
                 filing.reason)  # fmt: skip
        return filed

    # -- replaying ---------------------------------------------------------------------

    def ran_here(self, worker: str | None) -> bool:
        """Whether a trial filed by ``worker`` ran on this cluster."""
        return bool(worker) and str(worker).startswith(PREFIX)

    async def replay(self, trial: Trial) -> bytes:
        """Replay ``trial``'s record on another node than the one that ran it (the same
        one only when no other has the resource); the verdict, saying where."""
        assert trial.mcap is not None and self._ray is not None

        def others(nodes: dict[str, str]) -> list[str]:
            elsewhere = [node for name, node in nodes.items() if name != trial.worker]
            return elsewhere[trial.id % len(elsewhere) :] if elsewhere else []

        done = await self._on_a_node("replay", others, trial.mcap, self.config.replay)
        verdict: bytes = done["verdict"]
        return verdict


def _on(node_id: str) -> Any:
    """Ray's placement on the node ``node_id`` and no other."""
    from ray.util.scheduling_strategies import (  # noqa: PLC0415 (the extra's)
        NodeAffinitySchedulingStrategy,
    )

    return NodeAffinitySchedulingStrategy(node_id, soft=False)


def _probe(address: str, seconds: float = 5.0) -> None:
    """Refuse at once an address where nothing listens (``ray.init`` would wait on it for
    minutes); ``auto`` and the like are Ray's to find."""
    host, colon, port = address.removeprefix("ray://").rpartition(":")
    if not colon or not port.isdigit():
        return
    try:
        socket.create_connection((host.strip("[]"), int(port)), timeout=seconds).close()
    except OSError as err:
        raise ClusterError(f"no Ray cluster answers at {address}: {err}") from None


class _Stop(Exception):
    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason


def verdict_node(verdict: bytes) -> str | None:
    """Where a replay verdict says it was replayed (None: not said)."""
    try:
        node = json.loads(verdict).get("node")
    except (ValueError, AttributeError):
        return None
    return node if isinstance(node, str) else None
