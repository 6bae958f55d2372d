"""The lab's replays of what others filed (``labd.replays``): what a cluster's nodes ran
is replayed there, as many at once as the cluster has slots; what a remote worker filed
is replayed here, one at a time; every record gets its one verdict, and one whose
replay failed is not retried in a loop. The index, the store and the hosts are stand-ins:
this is the loop's logic (the cluster's tests run the real thing)."""

from __future__ import annotations

import asyncio
import json
import threading
import time
from pathlib import Path
from types import SimpleNamespace

from labd.replays import LabReplays
from repository.index import Derived

VERDICT = json.dumps({"verified": True}).encode()


class Records:
    """An index with finished records waiting for their verdicts."""

    def __init__(self, workers: dict[int, str]) -> None:
        self.workers = workers
        self.verdicts: dict[int, list[Derived]] = {}

    def unreplayed(self, trusted: tuple[str, ...], skip: set[int]) -> int | None:
        waiting = [t for t in self.workers if t not in self.verdicts and t not in skip]
        return min(waiting, default=None)

    def trial(self, trial_id: int) -> SimpleNamespace:
        return SimpleNamespace(id=trial_id, mcap="sha256:record", worker=self.workers[trial_id])

    def put_derived(self, trial_id: int, item: Derived) -> None:
        self.verdicts.setdefault(trial_id, []).append(item)


class Store:
    def copy_to(self, digest: str, dest: Path) -> Path:
        dest.write_bytes(b"record")
        return dest

    def put_file(self, path: Path) -> str:
        return "sha256:verdict"


class Counted:
    """How many calls are under way at once, at most."""

    def __init__(self) -> None:
        self.now = self.most = self.calls = 0
        self.lock = threading.Lock()

    def enter(self) -> None:
        with self.lock:
            self.now += 1
            self.calls += 1
            self.most = max(self.most, self.now)

    def leave(self) -> None:
        with self.lock:
            self.now -= 1


class Here:
    """This machine's replays (in a thread, as the helper process is waited on)."""

    def __init__(self) -> None:
        self.counted = Counted()

    def replay(self, mcap: Path, out: Path, *, seconds: float) -> SimpleNamespace:
        self.counted.enter()
        time.sleep(0.05)
        self.counted.leave()
        return SimpleNamespace(verdict=VERDICT)


class Cluster:
    """A cluster whose replays each wait until ``parallel`` of them are under way (or
    the last ones are): a loop that runs fewer at once never gets past the first."""

    def __init__(self, parallel: int, records: int, failing: set[int] = frozenset()) -> None:
        self.parallel = parallel
        self.records = records
        self.failing = failing
        self.counted = Counted()

    def ran_here(self, worker: str | None) -> bool:
        return bool(worker) and str(worker).startswith("ray:")

    async def replay(self, trial: SimpleNamespace) -> bytes:
        self.counted.enter()
        try:
            while self.counted.now < self.parallel and self.counted.calls < self.records:
                await asyncio.sleep(0.005)
            if trial.id in self.failing:
                raise ConnectionError("the node went away")
            return VERDICT
        finally:
            self.counted.leave()


async def replay_all(records: Records, tmp_path: Path, cluster: Cluster | None) -> LabReplays:
    here = Here()
    replays = LabReplays(
        records,  # type: ignore[arg-type]
        Store(),  # type: ignore[arg-type]
        here,  # type: ignore[arg-type]
        tmp_path,
        ("lab/",),
        poll=0.05,
        elsewhere=cluster,
    )
    replays.here = here  # type: ignore[attr-defined]
    stop = asyncio.Event()
    running = asyncio.create_task(replays.run(stop))
    expected = set(records.workers) - (cluster.failing if cluster else set())
    deadline = time.monotonic() + 30
    while set(records.verdicts) != expected:
        assert time.monotonic() < deadline, records.verdicts
        await asyncio.sleep(0.02)
    await asyncio.sleep(0.3)  # nothing more is replayed, nor retried
    stop.set()
    await asyncio.wait_for(running, 10)
    return replays


async def test_a_clusters_records_are_replayed_as_many_at_once_as_it_has_slots(tmp_path):
    workers = {t: "ray:aaaa" for t in range(1, 10)} | {10: "site-b@box", 11: "site-b@box"}
    records = Records(workers)
    cluster = Cluster(parallel=3, records=9, failing={4})
    replays = await replay_all(records, tmp_path, cluster)
    assert cluster.counted.most == 3  # never more than the cluster's slots, and that many
    assert cluster.counted.calls == 9  # each once: the failed one is not tried again
    assert replays.here.counted.most == 1 and replays.here.counted.calls == 2  # type: ignore[attr-defined]
    assert all(len(items) == 1 for items in records.verdicts.values())  # one verdict each
    assert 4 not in records.verdicts


async def test_without_a_cluster_records_are_replayed_one_at_a_time(tmp_path):
    records = Records({t: "site-b@box" for t in range(1, 5)})
    replays = await replay_all(records, tmp_path, None)
    assert replays.here.counted.most == 1 and replays.here.counted.calls == 4  # type: ignore[attr-defined]
