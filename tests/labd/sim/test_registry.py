"""Tasks as plugins: the registry loads the entry points of ``labd.tasks`` (one task or a
pack each), leaves out with its reason every plugin it cannot use (an import that
fails, no TaskSpec, a repeated name, a topic the lab keeps for itself), and the other
tasks go on working."""

from __future__ import annotations

import dataclasses
from importlib.metadata import EntryPoint, entry_points

import pytest

from labd.errors import UnknownTaskError
from labd.sim import registry
from labd.sim.base import ObservationTopic
from labd.sim.registry import GROUP, Registry
from tests.labd.sim.pointmass import TASK as POINTMASS
from tests.labd.sim.pointmass import PointMass

HERE = "tests.labd.sim.test_registry"


class Clashing(PointMass):
    observations = (
        *PointMass.observations,
        ObservationTopic("/clock", "rosgraph_msgs/msg/Clock", "x"),
    )


CLASHING = dataclasses.replace(POINTMASS, name="clashing", task_class=Clashing)
PACK = (
    dataclasses.replace(POINTMASS, name="puck-a"),
    dataclasses.replace(POINTMASS, name="puck-b"),
)
NOT_A_TASK = {"name": "pointmass"}
BAD_NAME = dataclasses.replace(POINTMASS, name="Point Mass")


def points(**targets: str) -> list[EntryPoint]:
    return [EntryPoint(name, value, GROUP) for name, value in targets.items()]


def test_the_labs_own_tasks_are_plugins_of_its_own_package():
    """The maze and the PR2 come from the entry points of the lab's own distribution."""
    own = {p.name: p.value for p in entry_points(group=GROUP) if p.value.startswith("labd.")}
    assert own["icreate-maze"] == "labd.sim.icreate.maze:TASK"
    assert own["pr2-table"] == "labd.sim.pr2.table:TASK"
    assert {"icreate-maze", "pr2-table"} <= set(registry.names())
    assert registry.problems() == {}


def test_one_task_a_pack_and_every_kind_of_bad_plugin():
    """Good plugins load (a pack gives each of its tasks); each bad one is left out with
    its reason, and the good ones still work."""
    found = Registry(
        lambda: points(
            pointmass=f"{HERE}:POINTMASS",
            pack=f"{HERE}:PACK",
            broken="tests.labd.sim.no_such_module:TASK",
            missing=f"{HERE}:NO_SUCH_ATTRIBUTE",
            dict=f"{HERE}:NOT_A_TASK",
            again=f"{HERE}:POINTMASS",
            clock=f"{HERE}:CLASHING",
            shouty=f"{HERE}:BAD_NAME",
        )
    )
    assert list(found.specs()) == ["pointmass", "puck-a", "puck-b"]
    problems = found.problems()
    said = {key.split(" = ")[0]: why for key, why in problems.items()}
    assert said["broken"].startswith("failed to import: ModuleNotFoundError")
    assert said["missing"].startswith("failed to import: AttributeError")
    assert said["dict"] == "names no TaskSpec (nor a tuple or list of them)"
    assert said["pointmass"] == "the task 'pointmass' is registered already; give it another name"
    assert said["clock"] == "declares /clock, which the lab keeps for itself"
    assert said["shouty"].startswith("its name must be lowercase letters")
    assert len(problems) == 6


def test_the_labs_own_tasks_win_a_name_taken_by_a_plugin():
    """A plugin that repeats the name of one of the lab's tasks is the one left out,
    whatever the order the entry points come in."""
    maze = dataclasses.replace(POINTMASS, name="icreate-maze")
    globals()["IMPOSTOR"] = maze
    try:
        found = Registry(
            lambda: points(
                **{"a-first": f"{HERE}:IMPOSTOR", "icreate-maze": "labd.sim.icreate.maze:TASK"}
            )
        )
        assert found.specs()["icreate-maze"].build is not maze.build
        assert list(found.problems()) == [f"a-first = {HERE}:IMPOSTOR ('icreate-maze')"]
    finally:
        del globals()["IMPOSTOR"]


def test_an_unknown_task_names_the_known_ones():
    """get() of a task nobody registered is UnknownTaskError listing the tasks."""
    with pytest.raises(UnknownTaskError, match=r"no task .roomba.; the tasks are .*icreate-maze"):
        registry.get("roomba")


def test_every_task_declares_what_the_lab_asks_of_it():
    """Each registered task declares its suites, and a live page among the lab's
    templates; the lab's own a layout, a camera and a default live robot too."""
    for name in registry.names():
        spec = registry.get(name)
        assert spec.suites, name
        assert spec.console.template.startswith("robot"), name
    for name in ("icreate-maze", "pr2-table"):
        spec = registry.get(name)
        assert spec.layout is not None and spec.layout.task == name
        assert spec.camera and spec.robot
    assert registry.default_robots() == [("icreate-1", "icreate-maze"), ("pr2-1", "pr2-table")]
