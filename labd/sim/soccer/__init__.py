"""Robot soccer: dm_control's ``locomotion.soccer`` as lab tasks ``soccer-NvN``.

Two teams of BoxHead walkers (a body that rolls, steers and kicks) on a pitch whose
size dm_control draws for the seed. Every topic of a team is under its side, ``/home``
or ``/away``: a lone controller plays home against a team that stands still, and a
match (two repositories) gives each team's session its own side (docs/tasks.md,
"Soccer"). ``task`` is the ``LabTask`` around dm_control's environment; ``TASKS`` are
the pack's ``TaskSpec``s, registered through the entry point group ``labd.tasks``.
"""

from __future__ import annotations

from labd.sim.registry import TaskSpec
from labd.sim.soccer.export import layout_of
from labd.sim.soccer.task import CAMERA, SIDES, SoccerTask, actions_of, task_class
from repository.evaluation import Suite

__all__ = ["SIDES", "TASKS", "SoccerTask"]

SUITES = (
    Suite(
        "dev",
        1,
        seeds=tuple(range(10)),
        doc="10 legs, seeds 0 to 9 (dm_control's random_state), default parameters",
    ),
    Suite("test", 1, episodes=20, held_out=True, doc="20 legs whose seeds are the lab's"),
)
TEAM_SIZES = (1, 2)


def spec_of(team_size: int) -> TaskSpec:
    cls = task_class(team_size)
    return TaskSpec(
        name=cls.name,
        version=cls.version,
        doc=f"dm_control's soccer, {team_size} BoxHead walker(s) a side: a leg ends at the "
        "first goal or after 45 s. Played alone, the away side stands still.",
        params=cls.params,
        build=cls.make,
        task_class=cls,
        suites=SUITES,
        layout=layout_of(cls.name, team_size),
        camera=CAMERA,
        actions=actions_of(team_size),
        normal_form=True,
        sides=SIDES,
    )


TASKS: tuple[TaskSpec, ...] = tuple(spec_of(size) for size in TEAM_SIZES)
