"""The dm_control suite pack: tasks of ``dm_control.suite`` as lab tasks ``dmc-DOMAIN-TASK``.

The pack's one contract (DESIGN.md, "Robots and time"; docs/tasks.md, "The dm_control
suite pack"):

- seed N is ``suite.load(domain, task, task_kwargs={"random": N})``;
- one lab tick is one step of that environment (its control timestep, its physics
  steps per tick, its episode length by default), so the same actions give the same
  rewards, bit for bit, as dm_control's own environment;
- commands on ``/action`` (``std_msgs/msg/Float64MultiArray``, in the action spec's
  order); observations on ``/observation/KEY`` (the same type, flattened) and
  ``/reward`` (``std_msgs/msg/Float64``), with ``/joint_states``, ``/tf`` and the suite's
  default camera;
- an episode succeeds when its return reaches the task's threshold.

``catalog`` lists the tasks as data (so importing the pack builds no environment),
``task`` is the ``LabTask`` around the suite's task, ``export`` the export layouts.
``TASKS`` are the pack's ``TaskSpec``s, registered through the entry point group
``labd.tasks``; ``benchmarks.BENCHMARKS`` its benchmarks (``dmc-classic``, ``dmc``),
through ``labd.benchmarks``.
"""

from __future__ import annotations

from labd.sim.dmc.catalog import CATALOG, Listing
from labd.sim.dmc.export import LAYOUTS, layout, layout_of
from labd.sim.dmc.task import SuiteTask, actions_of, task_class
from labd.sim.registry import TaskSpec
from repository.evaluation import Suite

__all__ = [
    "CATALOG",
    "LAYOUTS",
    "TASKS",
    "Listing",
    "SuiteTask",
    "actions_of",
    "layout",
    "layout_of",
]

SUITES = (
    Suite(
        "dev",
        1,
        seeds=tuple(range(20)),
        doc="20 episodes, seeds 0 to 19 (dm_control's random=0..19), default parameters",
    ),
    Suite("test", 1, episodes=50, held_out=True, doc="50 episodes whose seeds are the lab's"),
)


def spec_of(listing: Listing) -> TaskSpec:
    """The TaskSpec of one pack task."""
    cls = task_class(listing)
    return TaskSpec(
        name=listing.name,
        version=cls.version,
        doc=f"dm_control's {listing.domain} {listing.task} ({listing.goal}), solved at a return "
        f"of {listing.threshold:g} of 1000 in {listing.time_limit:g} s.",
        params=cls.params,
        build=cls.make,
        task_class=cls,
        suites=SUITES,
        layout=layout_of(listing),
        camera=listing.camera,
        actions=actions_of(listing),
        normal_form=True,
    )


TASKS: tuple[TaskSpec, ...] = tuple(spec_of(listing) for listing in CATALOG)
