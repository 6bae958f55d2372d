"""The lab's loop: demonstrations in, a controller that learns from them out.

Scripted drives of a live maze robot are filed as demonstrations; the kNN example, whose
lab.toml asks for the maze's successful demonstrations, is submitted (its data pinned
then, on SQLite and PostgreSQL), runs as a real sandboxed trial with the records in
LAB_DATA_DIR, reaches the goal of a maze it was shown where a random policy gets nowhere,
and its rerun learns from the same records (even after more were filed) and reproduces.
"""

from __future__ import annotations

import random
import shutil
from pathlib import Path

import pytest

from labd.graph.graph import Graph, Side
from labd.graph.types import TypeRegistry
from labd.live import Driving
from labd.scripted import demonstrate
from labd.service import Service, ServiceConfig
from labd.sim.robot import Robot
from labd.station import Station
from repository.index import Filters
from repository.trial import Kind, Status, TrialRequest
from scheduler.runner import RunOptions
from scheduler.worker import Worker, WorkerConfig
from tests.helpers.githttp import GitRepo
from tests.scheduler.conftest import make_backend

EXAMPLE = Path(__file__).resolve().parents[2] / "controllers" / "examples" / "knn-maze"
TASK = "icreate-maze"
SEED = 4
PARAMS: dict[str, float] = {}  # the task's defaults: 180 s


def random_reward(seed: int) -> float:
    """The reward of uniformly random commands on the same maze, in this process."""
    rng = random.Random(seed)
    graph = Graph(TypeRegistry.default(), name="random")
    robot = Robot(graph, TASK, PARAMS, seed)
    cmd = graph.create_node("/random", side=Side.CLIENT).advertise(
        "/cmd_vel", "geometry_msgs/msg/Twist"
    )
    try:
        robot.publish()
        while robot.sim.running:
            cmd.publish({"linear": {"x": rng.uniform(-0.5, 0.5)}, "angular": {"z": rng.uniform(-4, 4)}})
            robot.step()
        return float(robot.sim.metrics()["reward"])
    finally:
        robot.close()


async def run_next(service: Service, worker: Worker) -> int:
    claim = service.queue.claim(worker.config.name)
    assert claim is not None
    await worker.execute(claim)
    return claim.id


async def test_a_knn_controller_learns_from_pinned_demonstrations_and_reruns(
    database_url, cache, tmp_path
):
    """Demonstrations filed, the kNN submitted with them pinned, run sandboxed: it reaches
    the goal of a demonstrated maze, better than random; more demonstrations are filed;
    the rerun pins the same ones and reproduces."""
    service = Service(ServiceConfig(data=tmp_path / "lab", database=database_url, workers=0))
    service.index.add_user("knn", max_running=5)
    user = service.index.user("knn")
    station = Station(TypeRegistry.default(), "icreate-1", TASK, {}, 100, live=True,
                      protected_prefixes=())  # fmt: skip
    driving = Driving(station, work=tmp_path / "live", file=service.file_demonstration)
    try:
        mazes = [SEED, 11, 12, 13, 14]  # the trial's maze among others
        demos = [demonstrate(station, driving, user="ann", seed=s) for s in mazes]
        assert all(d is not None and d.achieved for d in demos)
        filed = [t.id for t in service.index.find(Filters(kind=Kind.DEMONSTRATION)).items]
        assert len(filed) == 5

        repo = tmp_path / "knn"
        shutil.copytree(EXAMPLE, repo)
        GitRepo.create(repo, {})
        GitRepo(repo).commit({"README.md": "a kNN from demonstrations\n"})
        request = TrialRequest(repository=str(repo), ref="main", params=PARAMS, seed=SEED)
        trial_id = service.submissions.submit(user, request)
        queued = service.index.trial(trial_id)
        assert [p.trial for p in queued.data or []] == sorted(filed)  # pinned when submitted
        assert {p.data_digest for p in queued.data or []} == {d.data_digest for d in demos if d}

        config = WorkerConfig(
            name="w", work=tmp_path / "work", cache=cache, options=RunOptions()
        )
        worker = Worker(service.queue, service.store, make_backend("bwrap", cache), service.host,
                        config)  # fmt: skip
        await run_next(service, worker)
        done = service.index.trial(trial_id)
        assert done.status is Status.FINISHED and done.outcome is not None, done.reason
        assert done.outcome.value == "success", done.reason
        assert done.manifest is not None
        assert done.manifest["data"] == [p.manifest_entry() for p in queued.data or []]
        assert done.reward is not None and done.reward > random_reward(SEED) + 10

        more = demonstrate(station, driving, user="ann")  # filed after: not learnt from
        assert more is not None
        again = service.submissions.rerun(user, trial_id)
        assert service.index.trial(again).data == queued.data
        await run_next(service, worker)
        rerun = service.index.trial(again)
        assert rerun.verdict == "reproduced", rerun.divergence
    finally:
        driving.close()
        station.close()
        service.index.close()
