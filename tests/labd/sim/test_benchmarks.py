"""Benchmarks as plugins: the registry loads the entry points of ``labd.benchmarks`` as it
loads those of ``labd.tasks``; the dm_control pack declares ``dmc-classic`` and ``dmc``;
a benchmark naming a task or suite the lab does not have, and a plugin it cannot use, are
left out with their reason (and a warning), and the others still work."""

from __future__ import annotations

import logging
from importlib.metadata import EntryPoint, entry_points

import pytest

from labd.errors import LabError
from labd.sim import registry
from labd.sim.dmc import CATALOG
from labd.sim.registry import BENCHMARK_GROUP, GROUP, Registry
from repository.benchmark import Benchmark, BenchmarkTask, By, Normalize

HERE = "tests.labd.sim.test_benchmarks"
CLASSIC = [
    "dmc-cartpole-balance",
    "dmc-cartpole-swingup",
    "dmc-pendulum-swingup",
    "dmc-reacher-easy",
    "dmc-point_mass-easy",
    "dmc-ball_in_cup-catch",
]
SCORE = Normalize(by=Normalize.SUCCESS)


def one(name: str, task: str, suite: str = "dev") -> Benchmark:
    return Benchmark(
        name=name, doc="d", tasks=(BenchmarkTask(task=task, suite=suite, normalize=SCORE),)
    )


GOOD = one("maze", "icreate-maze")
PACK = (one("pack-a", "dmc-cartpole-balance"), one("pack-b", "dmc-reacher-easy"))
MISSING_TASK = (one("ghost", "no-such-task"), one("kept", "pr2-table"))
MISSING_SUITE = one("nosuite", "dmc-cartpole-balance", suite="hard")
NOT_A_BENCHMARK = {"name": "maze"}


def points(**targets: str) -> list[EntryPoint]:
    return [EntryPoint(name, value, BENCHMARK_GROUP) for name, value in targets.items()]


def the_labs_tasks() -> list[EntryPoint]:
    return list(entry_points(group=GROUP))


def test_the_dm_control_pack_is_a_benchmark_plugin_of_the_labs_own_package():
    """The lab's distribution registers the pack's benchmarks under ``labd.benchmarks``."""
    own = {p.name: p.value for p in entry_points(group=BENCHMARK_GROUP)}
    assert own["suite"] == "labd.sim.dmc.benchmarks:BENCHMARKS"
    assert registry.benchmark_problems() == {}


def test_dmc_classic_and_dmc_are_the_packs_tasks_on_their_dev_suites_by_return():
    """dmc-classic has its six tasks and dmc all 26 of the pack, each a registered task
    with a dev suite, an episode scoring its return over 1000."""
    found = {b.name: b for b in registry.benchmarks()}
    assert list(found)[:2] == ["dmc-classic", "dmc"]
    assert [t.task for t in found["dmc-classic"].tasks] == CLASSIC
    assert [t.task for t in found["dmc"].tasks] == [listing.name for listing in CATALOG]
    assert len(found["dmc"].tasks) == 26
    for benchmark in (found["dmc-classic"], found["dmc"]):
        for each in benchmark.tasks:
            assert registry.get(each.task).suite(each.suite) is not None
            assert each.suite == "dev"
            assert each.normalize == Normalize(by=By.RETURN, scale=1000.0)
    assert registry.benchmark("dmc-classic") is found["dmc-classic"]


def test_an_unknown_benchmark_names_the_known_ones():
    """Asking for a benchmark the lab lacks is a LabError naming the ones it has."""
    with pytest.raises(LabError, match=r"no benchmark 'dmc-clasic' \(did you mean dmc-classic\?\)"):
        registry.benchmark("dmc-clasic")
    with pytest.raises(LabError, match="the benchmarks are dmc-classic, dmc"):
        registry.benchmark("atari")


def test_a_benchmark_the_lab_cannot_run_is_left_out_with_a_warning(caplog):
    """A benchmark naming a missing task or suite, a repeated name, a plugin that fails
    to import or names no Benchmark: each is left out, said and logged; the rest load."""
    found = Registry(
        the_labs_tasks,
        lambda: points(
            good=f"{HERE}:GOOD",
            pack=f"{HERE}:PACK",
            missing=f"{HERE}:MISSING_TASK",
            nosuite=f"{HERE}:MISSING_SUITE",
            again=f"{HERE}:GOOD",
            broken="tests.labd.sim.no_such_module:BENCHMARKS",
            dict=f"{HERE}:NOT_A_BENCHMARK",
        ),
    )
    with caplog.at_level(logging.WARNING, logger="labd.sim.registry"):
        # in the order of the entry points' names: "again" declares maze first
        assert list(found.benchmarks()) == ["maze", "kept", "pack-a", "pack-b"]
    said = {key.split(" = ")[0]: why for key, why in found.benchmark_problems().items()}
    assert said["missing"] == "names the task 'no-such-task', which this lab does not have"
    assert said["nosuite"] == (
        "names the suite 'hard' of dmc-cartpole-balance, which has no such suite"
    )
    assert said["good"] == "the benchmark 'maze' is declared already; give it another name"
    assert said["broken"].startswith("failed to import: ModuleNotFoundError")
    assert said["dict"] == "names no Benchmark (nor a tuple or list of them)"
    assert len(said) == 5
    logged = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert any("no-such-task" in m and "left out" in m for m in logged)
    assert found.specs().keys() >= {"icreate-maze", "dmc-cartpole-balance"}  # tasks unharmed
