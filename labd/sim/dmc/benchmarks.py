"""The dm_control pack's benchmarks, registered through the entry point group
``labd.benchmarks`` (``labd.sim.registry``).

Each task is on its public ``dev`` suite (20 episodes, seeds 0 to 19), and an episode
scores its return over 1000, clipped to [0, 1]: the suite's rewards are each in [0, 1]
over its 1000 steps, so 1000 is the most any episode can earn, as the literature
normalizes the suite (rliable's DMC scores).
"""

from __future__ import annotations

from labd.sim.dmc.catalog import CATALOG
from repository.benchmark import Benchmark, BenchmarkTask, Normalize

RETURN_OVER_1000 = Normalize(by=Normalize.RETURN, scale=1000.0)
# the six tasks most papers on the suite report, as dm_control names them
CLASSIC = (
    "cartpole-balance",
    "cartpole-swingup",
    "pendulum-swingup",
    "reacher-easy",
    "point_mass-easy",
    "ball_in_cup-catch",
)


def _on_dev(names: tuple[str, ...]) -> tuple[BenchmarkTask, ...]:
    return tuple(BenchmarkTask(task=n, suite="dev", normalize=RETURN_OVER_1000) for n in names)


BENCHMARKS: tuple[Benchmark, ...] = (
    Benchmark(
        name="dmc-classic",
        doc="Six classic tasks of the DeepMind Control Suite (cartpole balance and swing-up,"
        " pendulum swing-up, reacher easy, point mass easy, ball in cup catch), each on its"
        " dev suite, an episode scoring its return over 1000.",
        tasks=_on_dev(tuple(f"dmc-{name}" for name in CLASSIC)),
    ),
    Benchmark(
        name="dmc",
        doc=f"All {len(CATALOG)} tasks of the dm_control suite pack, each on its dev suite,"
        " an episode scoring its return over 1000.",
        tasks=_on_dev(tuple(listing.name for listing in CATALOG)),
    ),
)
