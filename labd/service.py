"""The lab as a service: the archive's index and blobs, the queue, and its workers.

``labd serve`` builds one ``Service`` beside the bridge, and the HTTP API answers from
it. By default everything is under the data folder: ``DATA/index.sqlite``,
``DATA/blobs/`` (the content-addressed store), ``DATA/cache/`` (git mirrors, controller
runtimes) and ``DATA/work/`` (trials while they run). A database URL and a blob store
URL put the index on PostgreSQL and the blobs in an S3-compatible bucket.

Workers in the service are named ``HOST:PID/local-N``. When ``labd serve`` starts, the
trials that a previous ``labd serve`` on this host left running (it was killed) go back
to the queue at once, rather than when their lease runs out.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import os
import shutil
import socket
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import sandbox
from labd.cluster import Cluster, ClusterConfig, NodeSetup
from labd.config import DATA, database_url
from labd.graph.types import TypeRegistry
from labd.hosted import HostedRepos
from labd.live import Demonstration
from labd.metrics import LabMetrics
from labd.oidc import OidcConfig
from labd.replays import LabReplays
from labd.trial import LabHost, client_library
from labd.videos import Videos
from labd.workers import LOCAL_WORKERS, WorkerProcesses
from repository.accounts import Accounts
from repository.benchmark_index import BenchmarkRuns
from repository.blobs import BlobStore
from repository.errors import ArchiveError
from repository.evaluation_index import Evaluations
from repository.index import Derived, Index
from repository.match_index import Matches
from repository.reservations import Reservations, Rules, load_secret
from repository.signing import Keyring
from repository.trial import Ending, Filing
from repository.well_known import RECORD_FILE, REPLAY
from scheduler.benchmarks import BenchmarkRunner
from scheduler.data import DataPolicy, LocalArchive
from scheduler.errors import InvalidRequest
from scheduler.evaluate import Evaluator, HeldOutBudget
from scheduler.fetch import FetchPolicy
from scheduler.filing import FilingCheck
from scheduler.matches import Matchmaker
from scheduler.queue import Queue, QueueConfig
from scheduler.runner import RunOptions
from scheduler.submit import Submissions
from scheduler.worker import Worker, WorkerConfig

log = logging.getLogger("labd.service")


@dataclass(frozen=True)
class ServiceConfig:
    data: Path = DATA
    database: str | None = None  # SQLAlchemy URL; default sqlite:///DATA/index.sqlite
    blobs: str | None = None  # folder or fsspec URL; default DATA/blobs
    blob_options: Mapping[str, Any] = field(default_factory=dict)
    cache: Path | None = None  # mirrors and runtimes; default DATA/cache
    keys: Path | None = None  # the keys the lab signs records with; default DATA/keys
    workers: int = 1
    sandbox: str | None = None  # docker, bwrap, or None: docker if it answers
    queue: QueueConfig = field(default_factory=QueueConfig)
    heartbeat: float = 10.0
    fetch: FetchPolicy = field(default_factory=FetchPolicy)
    run: RunOptions = field(default_factory=RunOptions)
    data_policy: DataPolicy = field(default_factory=DataPolicy)  # how much [data] a trial pins
    canaries: tuple[int, ...] = ()  # reference trials each worker reruns (canary.py)
    canary_every: float = 3600.0  # seconds between a worker's canary reruns
    rules: Rules = field(default_factory=Rules)  # booking live robots
    signup: bool = False  # people may make their own accounts on the sign-in page
    oidc: OidcConfig = field(default_factory=OidcConfig)  # signing in through OpenID providers
    submit_threads: int = 8  # submissions resolved at once (each may wait on a git server)
    submit_waiting: int = 64  # more that wait for a thread; past these, 503
    videos: str = "background"  # or "asked": render a record's video only when asked for
    worker_processes: int = 0  # workers in processes of their own (labd.workers)
    worker_options: tuple[str, ...] = ()  # more labd worker options: what they may fetch
    # where people and workers reach the HTTP port (the playground's repositories are
    # recorded under it); None: the address the lab listens on
    public_url: str | None = None
    held_out: HeldOutBudget = field(default_factory=HeldOutBudget)  # evaluations of held-out suites
    ray_address: str | None = None  # run trials on this Ray cluster too (labd.cluster)

    @property
    def database_url(self) -> str:
        return database_url(self.data, self.database)

    @property
    def blobs_url(self) -> str:
        return self.blobs or str((self.data / "blobs").resolve())


class Verdicts:
    """Whether a replay verdict (a blob, by digest) says the replay verified; each blob is
    read once, since a digest's bytes never change."""

    LIMIT = 100_000  # verdicts remembered

    def __init__(self, store: BlobStore) -> None:
        self.store = store
        self._known: dict[str, tuple[bool | None, str | None]] = {}

    def __call__(self, digest: str) -> bool | None:
        return self._read(digest)[0]

    def node(self, digest: str) -> str | None:
        """The cluster's node the verdict says it was replayed on (None: not said)."""
        return self._read(digest)[1]

    def _read(self, digest: str) -> tuple[bool | None, str | None]:
        if digest in self._known:
            return self._known[digest]
        try:
            verdict = json.loads(self.store.read_bytes(digest))
            verified, node = verdict.get("verified"), verdict.get("node")
        except (ArchiveError, ValueError, AttributeError) as err:
            log.warning("replay verdict %s cannot be read: %s", digest, err)
            return None, None  # not remembered: the store may answer later
        found = (
            verified if isinstance(verified, bool) else None,
            node if isinstance(node, str) else None,
        )
        if len(self._known) >= self.LIMIT:
            self._known.clear()
        self._known[digest] = found
        return found


def host_prefix() -> str:
    return f"{socket.gethostname()}:"


class Service:
    """Index, blob store, queue, submissions and (after ``start``) workers."""

    def __init__(
        self,
        config: ServiceConfig,
        types: TypeRegistry | None = None,
        *,
        clock: Callable[[], float] = time.time,
    ) -> None:
        self.config = config
        self.host = LabHost(types)
        # the lab's user's alone (its index, keys); a sandbox reaches what it needs below
        # it through its mounts (sandbox.views), never through the folder's mode
        config.data.mkdir(mode=0o700, parents=True, exist_ok=True)
        self.cache = (config.cache or config.data / "cache").resolve()
        self.index = Index.open(config.database_url, clock=clock)
        self.store = BlobStore(config.blobs_url, dict(config.blob_options) or None)
        keys = (config.keys or config.data / "keys").resolve()
        self.keyring = Keyring(keys)
        self.keys = keys  # the folder of the lab's signing keys and secrets
        self.accounts = Accounts(self.index)
        self.reservations = Reservations(
            self.index, config.rules, load_secret(keys / "reservations.secret")
        )
        # Every filing, of the workers here and of remote ones, is held to its record
        # before the lab signs it (scheduler.filing).
        self.queue = Queue(
            self.index, config.queue, self.keyring, check=FilingCheck(self.store, self.host)
        )
        # The playground's repositories (labd.hosted), served read-only at /git.
        self.hosted = HostedRepos((config.data / "git").resolve())
        # However local paths are allowed, no submission reaches the lab's own files: its
        # mirrors of repositories (some private), runtimes, trials at work, keys, hosted
        # repositories (fetched over HTTP like any other), blobs.
        own: tuple[Path, ...] = (self.cache, (config.data / "work").resolve(), keys)
        own += (self.hosted.root,)
        if "://" not in config.blobs_url:
            own += (Path(config.blobs_url).resolve(),)
        self.fetch = replace(config.fetch, lab_folders=(*config.fetch.lab_folders, *own))
        self.run_options = config.run
        if config.run.fetch is not None:
            fetch = replace(config.run.fetch, lab_folders=self.fetch.lab_folders)
            self.run_options = replace(config.run, fetch=fetch)
        self.submissions = Submissions(
            self.queue,
            self.host,
            self.cache,
            self.fetch,
            archive=LocalArchive(self.index, self.store),
            data_policy=config.data_policy,
            threads=config.submit_threads,
            waiting=config.submit_waiting,
        )
        verdicts = Verdicts(self.store)
        self.evaluations = Evaluations(self.index, verdicts, replayed_on=verdicts.node)
        self.evaluator = Evaluator(
            self.submissions,
            self.evaluations,
            load_secret(keys / "suites.secret"),  # held-out suites' seeds derive from it
            self.keyring,
            config.held_out,
        )
        self.benchmark_runs = BenchmarkRuns(self.index, self.evaluations, self.host.benchmark)
        self.benchmarker = BenchmarkRunner(self.evaluator, self.benchmark_runs, self.keyring)
        self.matches = Matches(self.index, verdicts, self._sides)
        self.matchmaker = Matchmaker(self.submissions, self.matches, self.keyring)
        self.videos = Videos(
            self.index,
            self.store,
            self.host,
            (config.data / "work").resolve(),
            background=config.videos == "background",
            busy=lambda: bool(self.queue.queued() or self.queue.running_workers()),
        )
        self.name = f"{host_prefix()}{os.getpid()}"
        self.workers: list[Worker] = []
        self.ended_workers: set[str] = set()  # the workers whose loop ended (labd.health)
        self.processes: WorkerProcesses | None = None
        if config.worker_processes > 0:
            self.processes = WorkerProcesses(
                self.accounts,
                config.data.resolve(),
                config.worker_processes,
                cache=self.cache,
                heartbeat=config.heartbeat,
                sandbox=config.sandbox,
                options=config.worker_options,
            )
        self.git_url: str | None = None  # the hosted repositories' URL, once serving_at says
        self._tasks: list[asyncio.Task[None]] = []
        self._stop = asyncio.Event()
        self.metrics = LabMetrics(self)  # GET /metrics
        # "verified" is the lab's own word: it replays what workers elsewhere filed (its
        # own workers, here and in its worker processes, replay what they file)
        self.replays = LabReplays(
            self.index,
            self.store,
            self.host,
            (config.data / "work").resolve(),
            (f"{self.name}/", f"{LOCAL_WORKERS}@"),
            on_verdict=self.metrics.replayed,
        )
        self.queue.on_filed.append(self.replays.wake)
        self.cluster: Cluster | None = None
        if config.ray_address:
            self.cluster = Cluster(
                self.queue, ClusterConfig(config.ray_address), self._node_setup(), name=self.name
            )
            self.replays.elsewhere = self.cluster  # replayed on another of its nodes

    def _sides(self, task: str) -> Sequence[str]:
        """A task's sides, home first; none for a task this lab no longer has."""
        try:
            return self.host.sides(task)
        except InvalidRequest:
            return ()

    def _node_setup(self) -> NodeSetup:
        """What a cluster's node needs to run this lab's trials as its workers do."""
        return NodeSetup(
            blobs=self.config.blobs_url,
            blob_options=dict(self.config.blob_options),
            work=(self.config.data / "work").resolve(),
            cache=self.cache,
            sandbox=self.config.sandbox,
            options=self.run_options,
            heartbeat=self.config.heartbeat,
        )

    async def start(self) -> None:
        """Start rendering videos; requeue what a killed predecessor left running; start
        the workers."""
        self._tasks.append(asyncio.create_task(self.videos.run(self._stop), name="videos"))
        if self.config.workers <= 0 and self.cluster is None:
            self._start_replays()
            return
        released = await asyncio.to_thread(self._release_dead_workers)
        if released:
            log.warning("requeued trials a killed labd left running: %s", released)
        if self.cluster is not None:
            await asyncio.to_thread(self.cluster.connect)  # ClusterError: serve says why
            self._tasks.append(asyncio.create_task(self.cluster.run(self._stop), name="cluster"))
        self._start_replays()  # after the cluster is joined: it replays what its nodes ran
        if self.config.workers <= 0:
            return
        backend = await asyncio.to_thread(
            sandbox.backend, self.config.sandbox, self.cache, [client_library()]
        )
        work = (self.config.data / "work").resolve()
        work.mkdir(parents=True, exist_ok=True)
        for n in range(self.config.workers):
            worker = Worker(
                self.queue,
                self.store,
                backend,
                self.host,
                WorkerConfig(
                    name=f"{self.name}/local-{n + 1}",
                    work=work,
                    cache=self.cache,
                    heartbeat=self.config.heartbeat,
                    options=self.run_options,
                    canaries=self.config.canaries,
                    canary_every=self.config.canary_every,
                ),
            )
            self.workers.append(worker)
            task = asyncio.create_task(worker.run(self._stop), name=worker.config.name)
            task.add_done_callback(self._worker_ended)
            self._tasks.append(task)
        log.info("%d worker(s) on %s", len(self.workers), backend.name)

    def _start_replays(self) -> None:
        self._tasks.append(asyncio.create_task(self.replays.run(self._stop), name="replays"))

    def serving_at(self, url: str) -> None:
        """The lab's HTTP port answers at ``url`` (known once it listens): its hosted
        repositories are at ``PUBLIC/git/`` (``public_url``, else ``url``), which this
        lab's submissions and workers fetch like any repository, over git's HTTP, from
        ``url`` itself (the public name or port may not lead back here: a container's
        port published under another number), except under TLS, whose certificate names
        the public host."""
        self.git_url = f"{(self.config.public_url or url).rstrip('/')}/git"
        at = f"{self.git_url}/" if url.startswith("https:") else f"{url.rstrip('/')}/git/"
        hosted = (f"{self.git_url}/",)
        self.fetch = replace(self.fetch, hosted=hosted, hosted_at=at)
        self.submissions.policy = replace(self.submissions.policy, hosted=hosted, hosted_at=at)
        if self.run_options.fetch is not None:
            fetch = replace(self.run_options.fetch, hosted=hosted, hosted_at=at)
            self.run_options = replace(self.run_options, fetch=fetch)
        if self.cluster is not None:
            self.cluster.node = self._node_setup()

    async def start_processes(self, server: str, env: dict[str, str] | None = None) -> None:
        """Start the worker processes, against this lab's HTTP API at ``server``, with
        ``env`` added to their environment."""
        if self.processes is not None:
            await self.processes.start(server, env)

    def _worker_ended(self, task: asyncio.Task[None]) -> None:
        """A worker's loop ends only when the service stops; anything else is a bug, logged."""
        self.ended_workers.add(task.get_name())
        if not task.cancelled() and task.exception() is not None:
            log.error("worker %s died", task.get_name(), exc_info=task.exception())

    def _release_dead_workers(self) -> list[int]:
        """Requeue trials held by workers of this host whose process is gone."""
        released = []
        for worker in self.queue.running_workers():
            host, _, rest = worker.partition(":")
            pid = rest.partition("/")[0]
            if host + ":" != host_prefix() or not pid.isdigit():
                continue
            if _alive(int(pid)) and int(pid) != os.getpid():  # ours: a predecessor's pid
                continue
            released += self.queue.release_worker(f"{host}:{pid}/")
        return released

    def file_demonstration(self, demo: Demonstration) -> int:
        """File a live robot's drive in the archive as a trial of kind ``demonstration``;
        its id. Blocking (the record goes to the blob store): call it from a thread."""
        mcap = demo.folder / RECORD_FILE
        filing = Filing(
            **(
                Ending.success(demo.reason) if demo.achieved else Ending.fail(demo.reason)
            ).model_dump(),
            manifest=demo.manifest.to_json(),
            manifest_digest=demo.manifest_digest,
            data_digest=demo.data_digest,
            digest_topics=demo.digest_topics,
            metrics=demo.metrics,
            backend="live",
            mcap=self.store.put_file(mcap),
            mcap_size=mcap.stat().st_size,
        )
        trial_id = self.queue.file_finished(demo.order, submitter=demo.user, filing=filing)
        log.info("demonstration %d filed: %s drove %s", trial_id, demo.user, demo.robot)
        try:
            self._replay(trial_id, mcap)
        except Exception:  # the drive is filed; its page says "not replayed"
            log.exception("demonstration %d: its replay could not be filed", trial_id)
        finally:
            shutil.rmtree(demo.folder, ignore_errors=True)
        return trial_id

    def _replay(self, trial_id: int, mcap: Path) -> None:
        """Replay a filed record here (as a worker does after filing) and keep the
        verdict beside it (its video is rendered later: ``labd.videos``)."""
        folder = mcap.with_name("replay")
        done = self.host.replay(mcap, folder)
        folder.mkdir(exist_ok=True)
        verdict_file = folder / REPLAY
        verdict_file.write_bytes(done.verdict)
        self.index.put_derived(
            trial_id,
            Derived(
                REPLAY, self.store.put_file(verdict_file), len(done.verdict), "application/json"
            ),
        )
        self.metrics.replayed(done.verdict)

    def wake(self) -> None:
        """A trial was queued: let idle workers claim it now."""
        for worker in self.workers:
            worker.wake.set()
        if self.cluster is not None:
            self.cluster.wake.set()

    async def close(self) -> None:
        """Stop the workers; trials they held go back to the queue at once."""
        if self.processes is not None:
            await self.processes.close()
        self._stop.set()
        for task in self._tasks:
            task.cancel()
        for task in self._tasks:
            with contextlib.suppress(asyncio.CancelledError):
                await task
        await self.videos.close()
        if self.workers or self.cluster is not None:
            await asyncio.to_thread(self.queue.release_worker, self.name + "/")
        if self.cluster is not None:
            await asyncio.to_thread(self.cluster.close)
        self.submissions.close()
        self.index.close()


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True
