"""The benchmarks' API (``labd.api.benchmarks``): every benchmark of the task packs with
its tasks, suites and normalization, one by name, and a 404 naming the known ones."""

# ruff: noqa: F811 (the API's fixtures, imported from test_api, are the tests' arguments)
from __future__ import annotations

from labd.sim import registry
from repository.benchmark import BenchmarkList
from tests.labd.test_api import api, service  # noqa: F401 (fixtures)


async def test_the_benchmarks_are_listed_with_their_tasks_suites_and_normalization(api):
    """GET /api/benchmarks is the registry's benchmarks, the dm_control pack's among
    them, each task with its suite and how an episode is normalized."""
    answer = await api.get("/api/benchmarks")
    assert answer.status_code == 200
    listed = answer.json()
    assert [b["name"] for b in listed] == [b.name for b in registry.benchmarks()]
    assert BenchmarkList.model_validate(listed).root == registry.benchmarks()
    classic = next(b for b in listed if b["name"] == "dmc-classic")
    assert classic["doc"].startswith("Six classic tasks of the DeepMind Control Suite")
    assert len(classic["tasks"]) == 6
    assert classic["tasks"][0] == {
        "task": "dmc-cartpole-balance",
        "suite": "dev",
        "normalize": {"by": "return", "scale": 1000.0},
    }
    assert len(next(b for b in listed if b["name"] == "dmc")["tasks"]) == 26


async def test_one_benchmark_by_name_and_an_unknown_one_is_404(api):
    """GET /api/benchmarks/{name} is that benchmark with its leaderboard (none run yet:
    empty); an unknown name is a 404 whose words name the benchmarks the lab has."""
    answer = await api.get("/api/benchmarks/dmc")
    assert answer.status_code == 200
    assert answer.json() == {**registry.benchmark("dmc").model_dump(mode="json"), "leaderboard": []}
    missing = await api.get("/api/benchmarks/dmc-clasic")
    assert missing.status_code == 404
    said = missing.json()["error"]
    assert "no benchmark 'dmc-clasic' (did you mean dmc-classic?)" in said
    assert "the benchmarks are dmc-classic, dmc" in said
