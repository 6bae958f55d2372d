"""The lab on a Ray cluster: ``labd serve --ray-address`` with no workers of its own, on a
local cluster bound to 127.0.0.1 (a head with no CPU, nodes of one CPU and one
``labd_sim`` slot each). An evaluation's episodes spread over the nodes and are filed
once each; a node lost mid-way loses no episode and files none twice; each record is
replayed on another node than the one that ran it; a lab killed mid-evaluation and
started again on its data finishes it, the episodes it had under way run again and
every one filed once; a rerun on the other node than its trial's reproduces it, the
same data digest; a cancelled evaluation's tasks stop; a lab without a cluster says so
in one line."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from collections.abc import Iterator
from typing import Any

import httpx
import pytest

from labd.cluster import node_name
from repository.index import Index
from repository.well_known import SUMMARY
from tests.helpers.timing import SECOND
from tests.integration.test_evaluate import BRIEF, LAB_TOML
from tests.integration.test_service import make_repo
from tests.labd.test_metrics import samples

ray = pytest.importorskip("ray", reason="the cluster's tests need labd[cluster] (make setup)")
from ray.cluster_utils import Cluster  # noqa: E402
from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy  # noqa: E402

pytestmark = [
    pytest.mark.integration,
    pytest.mark.timeout(900),
    pytest.mark.xdist_group("ray"),  # one cluster at a time on this machine
]
SLOW = BRIEF.replace("for _ in range(5):", "import time\n    time.sleep(2)\n    for _ in range(5):")


@pytest.fixture(scope="module")
def cluster() -> Iterator[Cluster]:
    """A head with no CPU and two nodes of one slot, on loopback only."""
    before = os.environ.get("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER")
    os.environ["RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"] = "0"  # keep every node on 127.0.0.1
    made = Cluster(initialize_head=True, head_node_args={"num_cpus": 0, "include_dashboard": False})
    try:
        for _ in range(2):
            made.add_node(num_cpus=1, resources={"labd_sim": 1})
        made.wait_for_nodes()
        yield made
    finally:
        made.shutdown()
        if before is None:
            os.environ.pop("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", None)
        else:
            os.environ["RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"] = before


def get(lab: Any, path: str) -> Any:
    answer = httpx.get(
        lab.server + path, headers={"Authorization": f"Bearer {lab.token}"}, timeout=30
    )
    assert answer.status_code == 200, (path, answer.text)
    return answer.json()


def wait(what: str, found: Any, timeout: float, lab: Any = None) -> Any:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if value := found():
            return value
        time.sleep(0.5)
    said = "".join(lab.output[-60:]) if lab is not None else ""
    pytest.fail(f"waited {timeout:.0f} s for {what}; the lab said:\n{said}")


def replay_nodes(lab: Any, rows: list[dict[str, Any]]) -> dict[int, str]:
    """Each episode's trial -> the node its replay ran on (all verified)."""
    nodes = {}
    for row in rows:
        verdict = get(lab, f"/api/trials/{row['trial']}/replay")
        assert verdict["verified"] is True, verdict
        nodes[row["trial"]] = verdict["node"]
    return nodes


def test_an_evaluation_runs_on_the_cluster_and_survives_a_lost_node(
    cluster, make_served_lab, tmp_path
):
    """The bar: 20 episodes over two nodes; one node removed mid-way and another added;
    every episode filed once, by a node, verified, most replays on another node."""
    lab = make_served_lab("--workers", "0", "--ray-address", cluster.address)
    repo = make_repo(tmp_path / "slow", {"lab.toml": LAB_TOML, "c.py": SLOW})
    queued = lab.json("evaluate", str(repo), "--suite", "dev")
    evaluation = queued["id"]

    def filed() -> list[dict[str, Any]]:
        rows = get(lab, f"/api/evaluations/{evaluation}")["rows"]
        return [r for r in rows if r["outcome"] is not None]

    wait("three episodes filed", lambda: len(filed()) >= 3, 300 * SECOND, lab)
    # what an operator watches: two nodes, two slots, this lab's trials running there
    metrics = samples(httpx.get(lab.server + "/metrics", timeout=30).text)
    assert metrics["labd_cluster_nodes"][()] == 2, metrics
    slots = {labels[0][1]: value for labels, value in metrics["labd_cluster_slots"].items()}
    assert slots["total"] == 2 and 0 <= slots["free"] <= 2 and 0 <= slots["running"] <= 2
    ready = httpx.get(lab.server + "/readyz", timeout=30)
    assert ready.status_code == 200 and "2 node(s)" in ready.json()["checks"]["cluster"], ready.text
    lost = next(node for node in cluster.worker_nodes)
    cluster.remove_node(lost)  # as a machine that dies: its tasks are run again elsewhere
    added = cluster.add_node(num_cpus=1, resources={"labd_sim": 1})

    def ended() -> dict[str, Any] | None:
        found: dict[str, Any] = get(lab, f"/api/evaluations/{evaluation}")
        return found if found["status"] == "finished" else None

    done = wait("the evaluation's end", ended, 600 * SECOND, lab)
    rows = done["rows"]
    assert len(rows) == 20 and len({r["trial"] for r in rows}) == 20
    assert {r["outcome"] for r in rows} == {"fail"}, rows  # the controller's, never the lab's
    trials = {r["trial"]: get(lab, f"/api/trials/{r['trial']}") for r in rows}
    ran_on = {t: row["worker"] for t, row in trials.items()}
    assert all(w.startswith("ray:") for w in ran_on.values()), ran_on
    assert node_name(lost.node_id) in ran_on.values(), ran_on  # before it was lost
    assert node_name(added.node_id) in ran_on.values(), ran_on  # once it was there
    log = "".join(lab.output)
    for trial in trials:
        assert log.count(f"trial {trial} fail on ray:") == 1, trial  # filed once each

    def replayed() -> bool:
        rows = get(lab, f"/api/evaluations/{evaluation}")["rows"]
        return all(r["verified"] is not None for r in rows)

    wait("every replay's verdict", replayed, 300 * SECOND, lab)
    nodes = replay_nodes(lab, rows)
    elsewhere = sum(nodes[t] != ran_on[t] for t in trials)
    assert elsewhere >= 15, (nodes, ran_on)  # most: a node may have been alone a while
    # each record's page summary, made on the cluster once its trial was filed (a task
    # the trial's node may have died under is made on another)
    index = Index.open(f"sqlite:///{lab.data / 'index.sqlite'}")
    summarized = wait(
        "every page summary",
        lambda: all(SUMMARY in index.derived(t) for t in trials) or None,
        120 * SECOND,
        lab,
    )
    assert summarized and "could not be made on the cluster" not in "".join(lab.output)


def test_a_lab_restarted_mid_evaluation_picks_up(cluster, make_served_lab, tmp_path):
    """A lab killed while episodes run on the cluster and records wait for their replays,
    then started again on the same data: the episodes it had under way run again once
    their leases run out, and the evaluation ends with every episode filed once, by a
    node, and verified."""
    lab = make_served_lab("--workers", "0", "--ray-address", cluster.address)
    repo = make_repo(tmp_path / "slow", {"lab.toml": LAB_TOML, "c.py": SLOW})
    evaluation = lab.json("evaluate", str(repo), "--suite", "dev")["id"]

    def under_way() -> tuple[set[int], set[int]] | None:
        rows = get(lab, f"/api/evaluations/{evaluation}")["rows"]
        running = {r["trial"] for r in rows if r["status"] == "running"}
        filed = [r for r in rows if r["outcome"] is not None]
        unreplayed = {r["trial"] for r in filed if r["verified"] is None}
        return (running, unreplayed) if len(filed) >= 3 and running and unreplayed else None

    running, unreplayed = wait(
        "three episodes filed, others running, a replay to come", under_way, 300 * SECOND, lab
    )
    lab.kill()  # as a crash: its Ray driver dies, and the tasks it owned with it
    before = "".join(lab.output)
    lab.start()  # the same data folder, cache and token

    def ended() -> dict[str, Any] | None:
        found: dict[str, Any] = get(lab, f"/api/evaluations/{evaluation}")
        return found if found["status"] == "finished" else None

    done = wait("the evaluation's end", ended, 300 * SECOND, lab)
    rows = done["rows"]
    assert len(rows) == 20 and len({r["trial"] for r in rows}) == 20
    assert {r["outcome"] for r in rows} == {"fail"}, rows  # the controller's, never the lab's
    trials = {r["trial"]: get(lab, f"/api/trials/{r['trial']}") for r in rows}
    assert all(t["worker"].startswith("ray:") for t in trials.values()), trials
    after = "".join(lab.output)
    for trial in trials:
        assert (before + after).count(f"trial {trial} fail on ray:") == 1, trial  # filed once
    interrupted = {t for t in running if f"trial {t} fail on ray:" not in before}
    assert interrupted, (running, before)  # the kill caught episodes under way
    for trial in interrupted:
        assert trials[trial]["attempts"] == 2, trials[trial]  # run again, by the new lab
        assert f"trial {trial}: lease of worker" in after, trial

    def replayed() -> bool:
        rows = get(lab, f"/api/evaluations/{evaluation}")["rows"]
        return all(r["verified"] is not None for r in rows)

    left = sorted(unreplayed)
    wait(f"every replay's verdict (unreplayed at the kill: {left})", replayed, 180 * SECOND, lab)
    replay_nodes(lab, rows)  # all verified


def test_a_rerun_on_the_other_node_has_the_same_data_digest(cluster, make_served_lab, tmp_path):
    """A trial run on one node and rerun on the other reproduces it: the same data digest."""
    lab = make_served_lab("--workers", "0", "--ray-address", cluster.address)
    repo = make_repo(tmp_path / "brief", {"lab.toml": LAB_TOML, "c.py": BRIEF})
    trial = lab.json("submit", str(repo), "--wait", code=1)["id"]  # 1: the controller's fail
    original = get(lab, f"/api/trials/{trial}")
    nodes = {node_name(node.node_id): node.node_id for node in cluster.worker_nodes}
    assert original["worker"] in nodes, (original["worker"], nodes)

    @ray.remote(num_cpus=0, resources={"labd_sim": 1})
    class Slot:
        """Holds a node's one slot while it lives."""

        def taken(self) -> bool:
            return True

    ray.init(address=cluster.address, namespace="probe", log_to_driver=False)
    try:  # the original's node busy: the rerun can only run on the other
        there = NodeAffinitySchedulingStrategy(nodes[original["worker"]], soft=False)
        held = Slot.options(scheduling_strategy=there).remote()
        assert ray.get(held.taken.remote(), timeout=120 * SECOND)
        [rerun] = lab.json("rerun", str(trial), "--wait")  # 0: reproduced
    finally:
        ray.shutdown()
    assert rerun["rerun_of"] == trial
    rerun = get(lab, f"/api/trials/{rerun['id']}")
    assert rerun["worker"] in nodes and rerun["worker"] != original["worker"], (rerun, original)
    assert rerun["reproduced"] is True, rerun
    assert rerun["data_digest"] == original["data_digest"] is not None


CRASH = """\
from controllers.client import Lab

with Lab.connect() as lab:
    lab.step()
    raise SystemExit(3)  # the controller's own crash, after its first step
"""


def test_a_controllers_crash_is_its_outcome_never_retried(cluster, make_served_lab, tmp_path):
    """A controller that crashes on a node is filed once, as its error, on its first
    attempt: Ray retries a task whose node died, never one whose controller did."""
    lab = make_served_lab("--workers", "0", "--ray-address", cluster.address)
    repo = make_repo(tmp_path / "crash", {"lab.toml": LAB_TOML, "c.py": CRASH})
    done = lab.labd("submit", str(repo), "--wait", "--json", check=False)
    trial = get(lab, f"/api/trials/{json.loads(done.stdout)['id']}")
    assert trial["outcome"] == "error" and trial["worker"].startswith("ray:"), trial
    assert "3" in trial["reason"] and trial["attempts"] == 1, trial
    assert "the cluster could not run" not in trial["reason"], trial  # not the lab's fault
    assert "".join(lab.output).count(f"trial {trial['id']} error on ray:") == 1


def test_a_cancelled_evaluation_stops_its_tasks(cluster, make_served_lab, tmp_path):
    """Cancelling cancels the Ray tasks: the running episodes end cancelled, and the
    nodes' slots are free again."""
    lab = make_served_lab("--workers", "0", "--ray-address", cluster.address)
    stall = BRIEF.replace("for _ in range(5):", "import time\n    time.sleep(600)\n    for _ in range(5):")  # fmt: skip
    repo = make_repo(tmp_path / "stall", {"lab.toml": LAB_TOML, "c.py": stall})
    evaluation = lab.json("evaluate", str(repo), "--suite", "dev")["id"]

    def running() -> int:
        rows = get(lab, f"/api/evaluations/{evaluation}")["rows"]
        return sum(1 for r in rows if r["status"] == "running")

    wait("two episodes running", lambda: running() >= 2, 300 * SECOND)
    lab.labd("cancel", "--evaluation", str(evaluation))

    def ended() -> dict[str, Any] | None:
        found: dict[str, Any] = get(lab, f"/api/evaluations/{evaluation}")
        return found if found["status"] in ("cancelled", "partial") else None

    done = wait("the cancel", ended, 120 * SECOND)
    assert {r["status"] for r in done["rows"]} == {"cancelled"}, done["rows"]
    ray.init(address=cluster.address, namespace="probe", log_to_driver=False)
    try:
        wait(
            "the slots free",
            lambda: ray.available_resources().get("labd_sim", 0) >= 2,
            60 * SECOND,
        )
    finally:
        ray.shutdown()


def test_no_cluster_at_the_address_is_one_line(tmp_path):
    """A lab pointed at a cluster that is not there says so, and exits."""
    env = {**os.environ, "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER": "0"}
    done = subprocess.run(
        [sys.executable, "-m", "labd", "serve", "--data", str(tmp_path / "d"),
         "--http-port", "0", "--bridge-port", "0", "--no-robots", "--workers", "0",
         "--sandbox", "bwrap", "--ray-address", "127.0.0.1:9"],
        capture_output=True, text=True, timeout=300 * SECOND, env=env, check=False,
    )  # fmt: skip
    assert done.returncode != 0
    said = [line for line in done.stderr.splitlines() if "Ray cluster" in line]
    assert said and said[-1].startswith("labd serve: no Ray cluster answers at 127.0.0.1:9"), (
        done.stderr
    )
