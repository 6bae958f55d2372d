"""Benchmark runs through the HTTP API in process: a commit queued on every task of
dmc-classic's dev suites, its episodes filed as a worker files them; the run's IQM is
the trimmed mean recomputed from its episodes and inside its interval, the probability
that one run improves on another is the one recomputed from the episodes and inside
its interval, and the run is signed over its evaluations; what cannot run is refused
before anything is queued.

No workers run here: episodes are claimed and filed the way a worker files them.
"""

# ruff: noqa: F811 (the API's fixtures, imported from test_api, are the tests' arguments)
from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
from scipy import stats

from repository.trial import Filing
from tests.fakes import verify_episodes
from tests.helpers.githttp import GitRepo
from tests.labd.test_api import api, auth, service  # noqa: F401 (fixtures)

CLASSIC = 6  # dmc-classic's tasks
DEV = 20  # episodes of each task's dev suite


@pytest.fixture
def runner(service) -> str:
    """A token whose daily limit takes two runs of dmc-classic (240 episodes)."""
    return service.index.add_user("rita", max_daily=1000)


def controller(tmp_path: Path, name: str, toml: str = "") -> str:
    lab_toml = f'[controller]\ncommand = ["python", "c.py"]\ntask = "dmc-cartpole-balance"\n{toml}'
    files = {"lab.toml": lab_toml, "c.py": f"# {name}\n"}
    return str(GitRepo.create(tmp_path / name, files).path)


async def run(api: Any, token: str, repository: str, **body: Any) -> Any:
    return await api.post(
        "/api/benchmark-runs",
        json={"repository": repository, "benchmark": "dmc-classic", **body},
        headers=auth(token),
    )


def file_all(service: Any, reward_of: Any) -> None:
    """Claim every queued episode and file it, its return ``reward_of(claim)``, its
    replay verified."""
    service.queue.check = None
    while (claim := service.queue.claim("w")) is not None:
        reward = reward_of(claim)
        filing = Filing(
            status="finished",
            outcome="success" if reward >= 900 else "fail",
            reason=f"a return of {reward}",
            data_digest=f"{claim.id:064x}",
            metrics={"reward": reward},
        )
        assert service.queue.finish(claim.id, "w", filing)
        verify_episodes(service, [claim.id])


async def normalized_scores(api: Any, run: dict[str, Any]) -> list[list[float]]:
    """Each task's episodes' normalized scores, read back from its evaluation."""
    found = []
    for task in run["evaluations"]:
        evaluation = (await api.get(f"/api/evaluations/{task['evaluation']}")).json()
        found.append([min(max(r["reward"] / 1000, 0.0), 1.0) for r in evaluation["rows"]])
    return found


async def test_two_runs_of_dmc_classic_are_scored_and_compared_as_rliable_defines(
    api, service, runner, tmp_path
):
    a, b = controller(tmp_path, "strong"), controller(tmp_path, "weak")
    made = await run(api, runner, a)
    assert made.status_code == 201, made.text
    first = made.json()
    assert made.headers["location"].endswith(f"/api/benchmark-runs/{first['id']}")
    assert (first["status"], first["episodes"], first["done"]) == ("queued", CLASSIC * DEV, 0)
    assert [t["task"] for t in first["evaluations"]] == [
        "dmc-cartpole-balance", "dmc-cartpole-swingup", "dmc-pendulum-swingup",
        "dmc-reacher-easy", "dmc-point_mass-easy", "dmc-ball_in_cup-catch",
    ]  # fmt: skip
    tasks = {t["task"] for t in first["evaluations"]}
    listed = (await api.get("/api/trials", params={"limit": 200})).json()["trials"]
    assert {t["task"] for t in listed} == tasks  # each episode runs its own task (LAB_TASK)
    file_all(service, lambda claim: (claim.id * 389) % 1000 + 50.0 * (claim.order.seed % 3))
    second = (await run(api, runner, b)).json()
    file_all(service, lambda claim: (claim.id * 211) % 700)

    runs = []
    for made_run in (first, second):
        done = (await api.get(f"/api/benchmark-runs/{made_run['id']}")).json()
        assert (done["status"], done["done"], done["verified"]) == ("finished", CLASSIC * DEV, True)
        scores = await normalized_scores(api, done)
        pooled = [s for task in scores for s in task]
        assert done["iqm"] == pytest.approx(stats.trim_mean(pooled, 0.25), abs=1e-12)
        assert done["iqm_interval"][0] <= done["iqm"] <= done["iqm_interval"][1]
        assert done["mean"] == pytest.approx(sum(pooled) / len(pooled), abs=1e-12)
        assert done["mean_interval"][0] <= done["mean"] <= done["mean_interval"][1]
        fractions = [f for _, f in done["profile"]]
        assert fractions == sorted(fractions, reverse=True) and len(fractions) == 21
        statement = done["signature"]["statement"]
        assert statement["schema"] == "labd.benchmark-run/1"
        assert [e["evaluation"] for e in statement["evaluations"]] == [
            t["evaluation"] for t in done["evaluations"]
        ]
        assert all(e["signature"] for e in statement["evaluations"])  # covers each one's
        runs.append((done, scores))

    (run_a, a_scores), (run_b, b_scores) = runs
    compared = await api.get(
        "/api/benchmark-runs/compare", params={"a": run_a["id"], "b": run_b["id"]}
    )
    assert compared.status_code == 200, compared.text
    found = compared.json()
    expected = (
        sum(
            stats.mannwhitneyu(x, y).statistic / (len(x) * len(y))
            for x, y in zip(a_scores, b_scores, strict=True)
        )
        / CLASSIC
    )
    assert found["probability_of_improvement"] == pytest.approx(expected, abs=1e-12)
    low, high = found["interval"]
    assert low <= found["probability_of_improvement"] <= high and found["tasks"] == CLASSIC
    listed = (await api.get("/api/benchmark-runs", params={"benchmark": "dmc-classic"})).json()
    assert [r["id"] for r in listed["runs"]] == [run_b["id"], run_a["id"]]


async def test_what_cannot_run_is_refused_before_anything_is_queued(api, service, runner, tmp_path):
    picky = controller(tmp_path, "picky", 'tasks = ["dmc-cartpole-balance"]\n')
    refused = await run(api, runner, picky)
    assert refused.status_code == 422, refused.text
    said = refused.json()["error"]
    assert "lab.toml lists the tasks it supports (dmc-cartpole-balance)" in said
    assert "dmc-classic has 5 outside them" in said
    plain = controller(tmp_path, "plain")
    held_out = await run(api, runner, plain, suite="test")
    assert held_out.status_code == 422 and "is held out" in held_out.json()["error"]
    unknown = await run(api, runner, plain, benchmark="dmc-clasic")
    assert unknown.status_code == 422 and "did you mean dmc-classic" in unknown.json()["error"]
    assert service.queue.claim("w") is None  # nothing was queued
    running = (await run(api, runner, plain)).json()
    other = (await run(api, runner, plain)).json()
    early = await api.get(
        "/api/benchmark-runs/compare", params={"a": running["id"], "b": other["id"]}
    )
    assert early.status_code == 422 and "runs compare once they have ended" in early.text
