"""Canary reruns: a worker whose simulation drifted takes itself out of the pool, and the
lab's status says which worker and where its canary diverged."""

from __future__ import annotations

import asyncio

import pytest

from labd.trial import LabHost
from repository.blobs import BlobStore
from repository.index import Index
from repository.trial import Order, Outcome, Status
from scheduler.canary import State
from scheduler.queue import Queue
from scheduler.runner import RunOptions
from scheduler.worker import Worker, WorkerConfig
from tests.helpers.githttp import GitRepo

pytestmark = [pytest.mark.integration, pytest.mark.timeout(180)]
STEPS = """\
from controllers.client import Lab
with Lab.connect() as lab:
    for _ in range(8):
        lab.publish("/cmd_vel", "geometry_msgs/msg/Twist", {"linear": {"x": 0.3}, "angular": {"z": 0.4}})
        lab.step()
"""
TOML = '[controller]\ncommand = ["python", "c.py"]\ntask = "icreate-maze"\n'


class DriftedHost(LabHost):
    """A lab whose physics drifted: every joint a little more damped than the model says."""

    def open(self, setup, **kwargs):
        trial = super().open(setup, **kwargs)
        trial.station.robot.sim.physics.model.dof_damping[:] += 0.05
        return trial


@pytest.fixture
def queue_store_repo(tmp_path, cache, backend):
    index = Index.open(f"sqlite:///{tmp_path / 'index.sqlite'}")
    index.add_user("alice", max_running=5)
    queue = Queue(index)
    store = BlobStore(str(tmp_path / "blobs"))
    repo = GitRepo.create(tmp_path / "robot", {"lab.toml": TOML, "c.py": STEPS})
    yield queue, store, repo
    index.close()


def submit(queue, repo, seed=0):
    order = Order(
        repository=str(repo.path),
        ref="main",
        commit=repo.rev(),
        task="icreate-maze",
        seed=seed,
        public=True,
    )
    return queue.submit(queue.index.user("alice"), order)


def worker(name, queue, store, backend, host, tmp_path, cache, canaries=()):
    config = WorkerConfig(
        name=name,
        work=tmp_path / "work",
        cache=cache,
        poll=0.05,
        replay=0,
        options=RunOptions(),
        canaries=tuple(canaries),
    )
    (tmp_path / "work").mkdir(exist_ok=True)
    return Worker(queue, store, backend, host, config)


async def run_until(w, condition, timeout=90):
    stop = asyncio.Event()
    task = asyncio.create_task(w.run(stop))
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout
    try:
        while not condition():
            assert loop.time() < deadline, "the condition never held"
            await asyncio.sleep(0.05)
    finally:
        stop.set()
        await asyncio.wait_for(task, 30)


async def test_a_drifted_worker_takes_itself_out(queue_store_repo, backend, cache, tmp_path):
    """A reference trial reproduces on a sound worker, which goes on claiming; on a worker
    whose physics drifted it diverges: that worker reports itself out, naming the first
    difference, and claims nothing."""
    queue, store, repo = queue_store_repo
    reference = submit(queue, repo)
    first = worker("w1", queue, store, backend, LabHost(), tmp_path, cache)
    await run_until(first, lambda: queue.trial(reference).status.ended)
    assert queue.trial(reference).outcome is Outcome.FAIL  # eight steps, then it stops

    sound = worker("sound", queue, store, backend, LabHost(), tmp_path, cache, [reference])
    waiting = submit(queue, repo, seed=1)
    await run_until(sound, lambda: queue.trial(waiting).status.ended)
    assert (
        queue.health["sound"].state is State.OK
        and "1 canaries reproduced" in queue.health["sound"].detail
    )

    drifted = worker("drifted", queue, store, backend, DriftedHost(), tmp_path, cache, [reference])
    left = submit(queue, repo, seed=2)
    await run_until(drifted, lambda: queue.health.get("drifted", None) is not None
                    and queue.health["drifted"].state is State.OUT)  # fmt: skip
    health = queue.health["drifted"]
    assert health.detail.startswith(f"canary trial {reference} did not reproduce: diverged at tick")
    assert " is " in health.detail and " in a, " in health.detail  # the field and both values
    assert queue.trial(left).status is Status.QUEUED  # it claimed nothing
