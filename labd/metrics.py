"""The lab's metrics for Prometheus: ``GET /metrics`` in the text exposition format.

Each lab has one ``LabMetrics``, made by its ``Service``, with a ``CollectorRegistry`` of
its own (never the client library's global one). Most values are read when Prometheus
scrapes, from where the lab keeps them already, by one collector (``_Collector``):

- from the index, with a few GROUP BY queries: trials by kind, status and outcome,
  evaluations by status, reruns by verdict, the queue's depth and its oldest trial's
  wait (``labd_index_up`` is 0, and these are left out, when the index does not answer);
- the workers, as ``/readyz`` sees them (``labd.health.workers``);
- the bridge's clients and frames per robot: integers the bridge adds to as frames pass
  (``labd.bridge.server.Traffic``), so the hot path pays one addition per frame;
- who drives each live robot (``labd.live.Driving``); the blob store's errors
  (``BlobStore.errors``).

Two are observed as they happen, in this process since it started: each filed trial's
wall time (a histogram), and each replay verdict filed (by verdict).

Every name is documented in docs/metrics.md, and a test holds the two to each other.
The metrics count; they name no user, token or worker.
"""

from __future__ import annotations

import json
import logging
from collections import Counter
from collections.abc import Iterator, Mapping
from typing import TYPE_CHECKING, Any

import sqlalchemy as sa
from prometheus_client import CollectorRegistry, Histogram, generate_latest
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric
from prometheus_client.exposition import CONTENT_TYPE_PLAIN_0_0_4
from prometheus_client.registry import Collector

from labd import __version__
from labd.health import STATES, workers
from repository.errors import ArchiveError, IndexLost
from repository.index import Derived, hidden
from repository.tables import episodes, evaluations, trials
from repository.trial import Filing, Kind, Outcome, Status
from repository.well_known import REPLAY

if TYPE_CHECKING:
    from labd.bridge.server import Traffic
    from labd.cluster import Cluster
    from labd.live import Driving
    from labd.service import Service

log = logging.getLogger("labd.metrics")
CONTENT_TYPE = CONTENT_TYPE_PLAIN_0_0_4  # Prometheus' text format, which every scraper reads
# Seconds: a lockstep trial takes from a few seconds to the lab's time limit (an hour).
WALL_BUCKETS = (1, 2, 5, 10, 20, 30, 60, 120, 300, 600, 1200, 1800, 3600)
VERDICTS = ("verified", "diverged", "not_replayable", "unreadable")
STORE_ERRORS = ("read", "write", "corrupt")
QUEUED, RUNNING = Status.QUEUED.value, Status.RUNNING.value
FINISHED, CANCELLED = Status.FINISHED.value, Status.CANCELLED.value


class LabMetrics:
    """The metrics of the lab of ``service``; ``bridge`` and ``drives`` are given by the
    lab once it has them (``labd.lab``), and are empty without a bridge."""

    def __init__(self, service: Service) -> None:
        self.service = service
        self.registry = CollectorRegistry()
        self.bridge: Mapping[str, Traffic] = {}  # by robot (graph)
        self.drives: Mapping[str, Driving] = {}  # by live robot
        self.verdicts: Counter[str] = Counter()  # replay verdicts filed, by verdict
        self.wall = Histogram(
            "labd_trial_wall_seconds",
            "Wall time of each trial filed since the lab started (seconds)",
            buckets=WALL_BUCKETS,
            registry=self.registry,
        )
        self.registry.register(_Collector(self))
        service.queue.on_filed.append(self._filed)
        service.queue.on_derived.append(self._derived)

    def exposition(self) -> bytes:
        """The metrics now, in Prometheus' text format (``CONTENT_TYPE``)."""
        return generate_latest(self.registry)

    def replayed(self, verdict: bytes) -> None:
        """Count a replay verdict filed (the JSON of a record's ``replay.json``)."""
        self.verdicts[_verdict(verdict)] += 1

    def _filed(self, trial_id: int, filing: Filing) -> None:
        # a held-out episode's time is not shown, here either (they are its submitter's
        # only channel from the sandbox: docs/evaluations.md)
        if filing.wall_seconds is not None and not self.service.index.is_hidden(trial_id):
            self.wall.observe(filing.wall_seconds)

    def _derived(self, trial_id: int, item: Derived) -> None:
        if item.name != REPLAY:
            return
        try:
            verdict = self.service.store.read_bytes(item.digest)
        except ArchiveError as err:  # counted as unreadable; the store's error is counted too
            log.warning("trial %d: its replay verdict cannot be read: %s", trial_id, err)
            verdict = b""
        self.replayed(verdict)


def _verdict(body: bytes) -> str:
    try:
        found = json.loads(body)
    except ValueError:
        return "unreadable"
    verified = found.get("verified") if isinstance(found, dict) else None
    if verified is True:
        return "verified"
    if verified is False:
        return "diverged" if found.get("divergence") else "not_replayable"
    return "unreadable"


class _Collector(Collector):
    """Reads what a scrape shows from where the lab keeps it."""

    def __init__(self, metrics: LabMetrics) -> None:
        self.metrics = metrics

    def collect(self) -> Iterator[Metric]:
        metrics = self.metrics
        service = metrics.service
        info = GaugeMetricFamily("labd_build_info", "The lab's version", labels=["version"])
        info.add_metric([__version__], 1)
        yield info
        yield from _index(service)
        counted = workers(service)
        found = GaugeMetricFamily(
            "labd_workers", "Workers by kind and state", labels=["kind", "state"]
        )
        for kind, states in STATES.items():
            for state in states:
                found.add_metric([kind, state], counted[kind, state])
        yield found
        yield from _bridge(metrics.bridge)
        drivers = GaugeMetricFamily(
            "labd_live_drivers", "Clients driving each live robot (0 or 1)", labels=["robot"]
        )
        for robot, drive in metrics.drives.items():
            drivers.add_metric([robot], 0 if drive.current is None else 1)
        yield drivers
        verdicts = CounterMetricFamily(
            "labd_replay_verdicts",
            "Replay verdicts filed since the lab started, by verdict",
            labels=["verdict"],
        )
        for verdict in VERDICTS:
            verdicts.add_metric([verdict], metrics.verdicts[verdict])
        yield verdicts
        errors = CounterMetricFamily(
            "labd_blob_store_errors",
            "Failed operations of the blob store since the lab started",
            labels=["operation"],
        )
        for kind in STORE_ERRORS:
            errors.add_metric([kind], service.store.errors[kind])
        yield errors
        if service.cluster is not None:
            yield from _cluster(service.cluster)


def _cluster(cluster: Cluster) -> Iterator[Metric]:
    """The Ray cluster's nodes and slots, as the dispatcher last counted them."""
    slots = cluster.slots
    nodes = GaugeMetricFamily(
        "labd_cluster_nodes", "Live nodes of the Ray cluster with the lab's resource"
    )
    nodes.add_metric([], slots.nodes)
    yield nodes
    found = GaugeMetricFamily(
        "labd_cluster_slots",
        "The Ray cluster's slots for trials: total, free, and running this lab's trials",
        labels=["state"],
    )
    found.add_metric(["total"], slots.total)
    found.add_metric(["free"], slots.free)
    found.add_metric(["running"], slots.in_flight)
    yield found


def _bridge(traffic: Mapping[str, Traffic]) -> Iterator[Metric]:
    clients = GaugeMetricFamily(
        "labd_bridge_clients", "Clients connected to each robot's bridge", labels=["robot"]
    )
    received = CounterMetricFamily(
        "labd_bridge_messages_received",
        "WebSocket frames received from clients since the lab started",
        labels=["robot"],
    )
    sent = CounterMetricFamily(
        "labd_bridge_messages_sent",
        "WebSocket frames sent to clients since the lab started",
        labels=["robot"],
    )
    for robot, counts in traffic.items():
        clients.add_metric([robot], counts.clients)
        received.add_metric([robot], counts.received)
        sent.add_metric([robot], counts.sent)
    yield from (clients, received, sent)


def _index(service: Service) -> Iterator[Metric]:
    """The families read from the index, and whether it answered."""
    up = GaugeMetricFamily(
        "labd_index_up", "Whether the index answered this scrape and takes writes (1 or 0)"
    )
    try:
        service.index.check()
        writable = True
    except IndexLost:  # its files changed under the lab: still read, never written
        writable = False
    try:
        families = _from_index(service)
    except (sa.exc.SQLAlchemyError, OSError) as err:
        log.warning("metrics: the index does not answer: %s", err)
        up.add_metric([], 0)
        yield up
        return
    up.add_metric([], 1 if writable else 0)
    yield up
    yield from families


def _from_index(service: Service) -> list[Metric]:
    T, E = trials.c, evaluations.c
    now = service.index.clock()
    with service.index.engine.connect() as db:
        shown = ~hidden(T.id)  # held-out episodes: counted when their suite is retired
        by_state = db.execute(
            sa.select(T.kind, T.status, T.outcome, sa.func.count())
            .where(shown)
            .group_by(T.kind, T.status, T.outcome)
        ).all()
        waiting, oldest = db.execute(
            sa.select(sa.func.count(), sa.func.min(T.created)).where(T.status == QUEUED, shown)
        ).one()
        reruns = db.execute(
            sa.select(T.reproduced, sa.func.count())
            .where(T.rerun_of.is_not(None), T.status == FINISHED, T.reproduced.is_not(None))
            .group_by(T.reproduced)
        ).all()
        done = db.execute(
            sa.select(sa.func.count()).where(E.finished.is_not(None), ~_with_cancelled())
        ).scalar_one()
        open_ = db.execute(_evaluation_statuses()).all()
    counted: Counter[tuple[str, str, str]] = Counter()
    for kind, status, outcome, count in by_state:
        counted[kind, status, outcome or ""] += count
    found = GaugeMetricFamily(
        "labd_trials",
        "Trials in the archive by kind, status and outcome (outcome empty until finished)",
        labels=["kind", "status", "outcome"],
    )
    states = [(QUEUED, ""), (RUNNING, ""), (CANCELLED, "")]
    states += [(FINISHED, o.value) for o in Outcome]
    for kind in Kind:
        for status, outcome in states:
            found.add_metric([kind.value, status, outcome], counted[kind.value, status, outcome])
    for (kind, status, outcome), count in counted.items():  # anything else the index holds
        if (status, outcome) not in states or kind not in {k.value for k in Kind}:
            found.add_metric([kind, status, outcome], count)
    depth = GaugeMetricFamily("labd_queue_depth", "Trials waiting for a worker")
    depth.add_metric([], waiting)
    wait = GaugeMetricFamily(
        "labd_queue_oldest_wait_seconds",
        "How long the oldest queued trial has waited (seconds; 0 when none waits)",
    )
    wait.add_metric([], max(0.0, now - oldest) if oldest is not None else 0.0)
    verdicts: dict[bool, int] = {bool(r[0]): r[1] for r in reruns}
    rerun = GaugeMetricFamily("labd_reruns", "Finished reruns by verdict", labels=["verdict"])
    rerun.add_metric(["reproduced"], verdicts.get(True, 0))
    rerun.add_metric(["diverged"], verdicts.get(False, 0))
    by_status: Counter[str] = Counter({FINISHED: done})
    for row in open_:
        by_status[str(row[0])] += int(row[1])
    evaluated = GaugeMetricFamily("labd_evaluations", "Evaluations by status", labels=["status"])
    for status in Status:
        evaluated.add_metric([status.value], by_status[status.value])
    return [found, depth, wait, rerun, evaluated]


def _evaluation_statuses() -> sa.Select[tuple[Any, int]]:
    """Evaluations not known to be finished, counted by status: the status of each from
    its episodes' (``repository.evaluation.status_of``), in the database, so only the
    counts come back. An ended evaluation with no episode cancelled is counted apart."""
    T, E, ep = trials.c, evaluations.c, episodes.c

    def count_of(condition: sa.ColumnElement[bool]) -> sa.ColumnElement[int]:
        return sa.func.sum(sa.case((condition, 1), else_=0))

    each = (
        sa.select(
            E.cancel_requested.label("cancel"),
            sa.func.count(T.id).label("total"),
            count_of(T.status == QUEUED).label("queued"),
            count_of(T.status.in_([QUEUED, RUNNING])).label("open"),
            count_of(T.status == CANCELLED).label("cancelled"),
        )
        .select_from(
            evaluations.outerjoin(episodes, ep.evaluation_id == E.id).outerjoin(
                trials, T.id == ep.trial_id
            )
        )
        .where(sa.or_(E.finished.is_(None), _with_cancelled()))
        .group_by(E.id, E.cancel_requested)
        .subquery()
    )
    status = sa.case(
        (sa.and_(each.c.total > 0, each.c.queued == each.c.total, sa.not_(each.c.cancel)), QUEUED),
        (each.c.open > 0, RUNNING),
        (each.c.cancelled > 0, CANCELLED),
        else_=FINISHED,
    )
    return sa.select(status, sa.func.count()).select_from(each).group_by(status)


def _with_cancelled() -> sa.Exists:
    """Whether an evaluation has an episode cancelled (it is then ``cancelled``)."""
    ep, t = episodes.alias("cancelled_episode"), trials.alias("cancelled_trial")
    return sa.exists().where(
        ep.c.evaluation_id == evaluations.c.id, t.c.id == ep.c.trial_id, t.c.status == CANCELLED
    )
