"""The HTTP API of benchmarks: what each one is (issue 37).

A benchmark is a named set of tasks, each on one of its suites, whose episodes' scores
are normalized to [0, 1] (``repository.benchmark``); task packs declare them
(``labd.sim.registry``). Reading is public.

    GET /api/benchmarks          every benchmark: name, doc, tasks (suite, normalization)
    GET /api/benchmarks/{name}   one (404 naming the known ones)

The bodies are the declarations themselves (``Benchmark``, ``BenchmarkList``), as they
round-trip: ``labd tasks`` reads them back without loading this module's web server.
"""

from __future__ import annotations

from fastapi import APIRouter

from labd.api.errors import ApiError, responses
from labd.errors import LabError
from labd.sim import registry
from repository.benchmark import Benchmark, BenchmarkList

router = APIRouter(tags=["benchmarks"])


@router.get("/api/benchmarks")
def list_benchmarks() -> BenchmarkList:
    """Every benchmark of the lab's task packs, the lab's own first: its tasks, the suite
    of each, and how an episode's score is normalized to [0, 1]."""
    return BenchmarkList(registry.benchmarks())


@router.get("/api/benchmarks/{name}", responses=responses(404))
def one_benchmark(name: str) -> Benchmark:
    """One benchmark: its tasks, the suite of each, and how an episode is scored."""
    try:
        return registry.benchmark(name)
    except LabError as err:  # no benchmark of that name: the message names the known ones
        raise ApiError(404, str(err)) from None
