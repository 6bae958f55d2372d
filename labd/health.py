"""The lab's health as an operator's tools see it: ``/readyz``'s checks, and its workers.

``/healthz`` only says that the process answers. ``/readyz`` (``readiness``) says whether
the lab can do its work, checking three things, cheaply, each time it is asked:

- ``index``: the index answers: its files are still the ones it opened
  (``repository.wal``) and a one-row query succeeds (SQLite or PostgreSQL);
- ``store``: the blob store answers (``BlobStore.check``: a folder the lab may write
  in, or one listing of an object store);
- ``workers``: a worker can run trials: one of this process's (``--workers``) whose
  loop runs and whose canaries did not take it out of the pool, or a worker process
  (``--worker-processes``) or remote worker (``labd worker``) heard from (a claim, a
  lease renewed, a report) within one lease and not out of the pool.

A lab that runs no workers of its own (``--workers 0`` and no worker processes) is
ready without one, and says so: its workers reach it over the HTTP API, which a load
balancer or proxy closes to them while the lab says it is not ready, so that once they
were all gone they could never come back. Such a lab's workers are watched in its
metrics instead (``labd_workers``, docs/metrics.md).

Nothing here names a worker or a user: the answers are public, so they count.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass
from typing import TYPE_CHECKING

import sqlalchemy as sa

from labd.workers import LOCAL_WORKERS
from repository.errors import IndexLost
from repository.masking import mask_text, mask_url
from repository.tables import meta
from scheduler.states import State

if TYPE_CHECKING:
    from labd.cluster import Cluster
    from labd.service import Service

FORGET_LEASES = 10  # a worker not heard from for this many leases is forgotten
IN_PROCESS, PROCESS, REMOTE = "in_process", "process", "remote"
STOPPED, LOST = "stopped", "lost"  # an in-process worker's loop ended; a worker went quiet
# The states each kind of worker can be in (``State``'s, and one of its own).
STATES = {
    IN_PROCESS: (*(s.value for s in State), STOPPED),
    PROCESS: (*(s.value for s in State), LOST),
    REMOTE: (*(s.value for s in State), LOST),
}
AVAILABLE = frozenset({State.OK.value, State.CHECKING.value})  # can run trials, now or soon


@dataclass(frozen=True)
class Check:
    """One thing ``/readyz`` checks: whether it is ready, and what it found."""

    name: str
    ok: bool
    detail: str


def workers(service: Service) -> Counter[tuple[str, str]]:
    """The lab's workers now, counted by (kind, state): kinds ``in_process``,
    ``process`` and ``remote``; states those of ``STATES``."""
    found: Counter[tuple[str, str]] = Counter()
    local = {w.config.name for w in service.workers}
    for worker in service.workers:
        gone = worker.config.name in service.ended_workers
        found[IN_PROCESS, STOPPED if gone else worker.health.state.value] += 1
    queue = service.queue
    now = queue.clock()
    lease = queue.config.lease
    for name, when in list(queue.seen.items()):  # a copy: workers' threads add to it
        if name in local or name == f"{service.name}/ray":  # the cluster's: its own check
            continue
        if now - when > FORGET_LEASES * lease:
            queue.seen.pop(name, None)
            continue
        kind = PROCESS if name.startswith(f"{LOCAL_WORKERS}@") else REMOTE
        health = queue.health.get(name)
        if health is not None and health.state is State.OUT:
            state = State.OUT.value  # it said so, and claims nothing since
        elif now - when > lease:
            state = LOST
        else:
            state = health.state.value if health is not None else State.OK.value
        found[kind, state] += 1
    return found


def readiness(service: Service) -> list[Check]:
    """The checks of ``/readyz``: the index, the blob store, the workers."""
    checks = [_index(service), _store(service), _workers(service)]
    if service.cluster is not None:
        checks.append(_cluster(service.cluster))
    return checks


def _cluster(cluster: Cluster) -> Check:
    """The Ray cluster's nodes and slots, as the dispatcher last counted them."""
    slots = cluster.slots
    where = f"the Ray cluster at {mask_url(cluster.config.address)}"
    if not cluster.connected:
        return Check("cluster", False, f"{where} is not joined yet")
    if slots.total <= 0:
        resource = cluster.config.resource
        return Check("cluster", False, f"{where} has no node with {resource}: no trial can run")
    return Check(
        "cluster",
        True,
        f"{where}: {slots.nodes} node(s), {slots.free} of {slots.total} slot(s) free,"
        f" {slots.in_flight} trial(s) of this lab running there",
    )


def _index(service: Service) -> Check:
    index = service.index
    kind = "PostgreSQL" if index.engine.dialect.name == "postgresql" else "SQLite"
    try:
        index.check()
        with index.engine.connect() as db:
            schema = db.execute(sa.select(meta.c.value).where(meta.c.key == "schema")).scalar()
    except IndexLost as err:
        return Check("index", False, str(err))
    except (sa.exc.SQLAlchemyError, OSError) as err:
        return Check("index", False, f"the {kind} index does not answer: {_first_line(err)}")
    return Check("index", True, f"the {kind} index answers (schema {schema})")


def _store(service: Service) -> Check:
    store = service.store
    kind = "local" if store.local else store.url.partition("://")[0]
    try:
        store.check()
    except Exception as err:  # noqa: BLE001 - OSError, or an object store's own (botocore's)
        return Check("store", False, f"the {kind} blob store does not answer: {_first_line(err)}")
    return Check("store", True, f"the {kind} blob store answers")


def _workers(service: Service) -> Check:
    counts = workers(service)
    ready = {kind: 0 for kind in STATES}
    for (kind, state), count in counts.items():
        if state in AVAILABLE:
            ready[kind] += count
    words = {IN_PROCESS: "in this process", PROCESS: "in processes", REMOTE: "remote"}
    if sum(ready.values()):
        said = ", ".join(f"{n} {words[k]}" for k, n in ready.items() if n)
        return Check("workers", True, f"workers ready: {said}")
    config = service.config
    if config.workers <= 0 and config.worker_processes <= 0 and service.cluster is not None:
        return Check("workers", True, "this lab runs its trials on its Ray cluster (cluster)")
    if config.workers <= 0 and config.worker_processes <= 0:
        return Check(
            "workers",
            True,
            "this lab runs no workers of its own and no remote worker has claimed within"
            f" {service.queue.config.lease:g} s: trials wait for one (`labd worker --server`)",
        )
    trouble = ", ".join(f"{n} {words[k]} {state}" for (k, state), n in sorted(counts.items()))
    return Check(
        "workers",
        False,
        f"no worker can run trials ({trouble or 'none started yet'}); see GET /api/status",
    )


def _first_line(err: BaseException) -> str:
    text = str(err).strip().splitlines()
    # an object store's error may quote its endpoint's URL, credentials and all
    return mask_text(f"{type(err).__name__}: {text[0] if text else ''}")[:300]
