"""A repository's own interface definitions: registered for one trial, or refused with the
file and line at fault."""

from __future__ import annotations

import pytest

from labd.errors import InterfaceError, UnknownTypeError
from labd.graph.definitions import trial_types
from labd.graph.graph import Graph
from labd.graph.types import TypeRegistry

DEBUG = (
    "# what the planner thinks\nstring phase\nfloat64 cost\ngeometry_msgs/Point[] path\nStep last\n"
)
STEP = "uint8 KIND_MOVE=1\nuint8 kind\n"
RESET = "bool hard\n---\nbool ok\nstring message\n"
PLAN = "int32 steps\n---\nStep[] done\n---\nfloat32 progress\n"


def own(**extra: str) -> dict[str, str]:
    files = {
        "interfaces/planner_msgs/msg/Debug.msg": DEBUG,
        "interfaces/planner_msgs/msg/Step.msg": STEP,
        "interfaces/planner_msgs/srv/Reset.srv": RESET,
        "interfaces/planner_msgs/action/Plan.action": PLAN,
    }
    files.update(extra)
    return files


def test_own_types_are_registered_for_that_registry_alone(registry: TypeRegistry):
    """Messages, services and actions of a repository resolve in its registry, with their
    definitions for the record, and never in the lab's."""
    types = trial_types(registry, own())
    debug = types.message("planner_msgs/Debug")
    assert [f.name for f in debug.fields] == ["phase", "cost", "path", "last"]
    assert debug.field("last").message == "planner_msgs/msg/Step"
    assert types.message("planner_msgs/msg/Step").constants[0].name == "KIND_MOVE"
    assert [f.name for f in types.service("planner_msgs/srv/Reset").response.fields] == [
        "ok",
        "message",
    ]
    assert types.action("planner_msgs/action/Plan").result.fields[0].message == (
        "planner_msgs/msg/Step"
    )
    text = types.definition_text("planner_msgs/msg/Debug")
    assert "string phase" in text and "MSG: planner_msgs/Step" in text
    assert "MSG: geometry_msgs/Point" in text
    for lookup in (
        lambda: registry.message("planner_msgs/msg/Debug"),
        lambda: registry.service("planner_msgs/srv/Reset"),
        lambda: registry.action("planner_msgs/action/Plan"),
    ):
        with pytest.raises(UnknownTypeError):
            lookup()


def test_a_graph_with_own_types_publishes_them_as_cdr(registry: TypeRegistry):
    """A message of an own type is validated and serialized like a standard one, and the
    lab's types keep the lab's compiled codecs."""
    types = trial_types(registry, own())
    graph = Graph(types, name="own", clock=lambda: 0)
    got = []
    node = graph.create_node("/n")
    node.subscribe("/debug", "planner_msgs/msg/Debug", got.append)
    node.advertise("/debug", None).publish({"phase": "search", "path": [{"x": 1.0}]})
    assert got[0].data["path"][0]["x"] == 1.0 and got[0].cdr()
    assert graph.codec("std_msgs/msg/String") is Graph(registry).codec("std_msgs/String")


@pytest.mark.parametrize(
    ("path", "text", "where", "words"),
    [
        (
            "x/std_msgs/msg/Fancy.msg",
            "int32 a\n",
            "x/std_msgs/msg/Fancy.msg",
            "std_msgs is a package the lab already has",
        ),
        (
            "x/example_interfaces/srv/AddTwoInts.srv",
            "int64 a\n---\nint64 sum\n",
            "x/example_interfaces/srv/AddTwoInts.srv",
            "package the lab already has",
        ),
        ("x/lab_msgs/msg/Mine.msg", "int32 a\n", "x/lab_msgs/msg/Mine.msg", "already has"),
        (
            "x/mine/msg/Bad.msg",
            "int32 a\nint32 b=abc\n",
            "x/mine/msg/Bad.msg, line 2",
            "cannot parse",
        ),
        (
            "x/mine/msg/Bad.msg",
            "int32 a\n\n# about c\nstrin c\n",
            "x/mine/msg/Bad.msg, line 4",
            "c has the type mine/strin, which is neither a standard type nor one the repository"
            " defines ('strin' is no type name: a misspelt primitive type?)",
        ),
        (
            "x/mine/msg/Bad.msg",
            "Missing m\n",
            "x/mine/msg/Bad.msg, line 1",
            "m has the type mine/Missing",
        ),
        (
            "x/mine/srv/Bad.srv",
            "int32 a\n---\nint32 b\n---\nint32 c\n",
            "x/mine/srv/Bad.srv, line 4",
            "a .srv has 2 parts, so at most 1 ---",
        ),
        (
            "x/mine/action/Bad.action",
            "int32 a\n---\nint32 b\n",
            "x/mine/action/Bad.action",
            "a .action has 3 parts separated by lines of ---; this has 2 parts",
        ),
        (
            "x/mine/msg/Bad.msg",
            "int32 Speed\n",
            "x/mine/msg/Bad.msg, line 1",
            "'Speed' is not a field name",
        ),
        (
            "x/mine/msg/Bad.msg",
            "int32 a\nint32 a\n",
            "x/mine/msg/Bad.msg, line 2",
            "a is defined twice",
        ),
        ("x/mine/msg/Bad.msg", "int32[0] a\n", "x/mine/msg/Bad.msg, line 1", "fixed array of 0"),
        (
            "x/mine/msg/Bad.msg",
            "uint8 A=1\nuint8 B=one\n",
            "x/mine/msg/Bad.msg, line 2",
            "the constant B must be an integer (uint8), not 'one'",
        ),
        ("x/mine/msg/Bad.msg", "int8 A=300\n", "x/mine/msg/Bad.msg, line 1", "out of the range"),
        ("x/mine/msg/Bad.msg", "float64 F=x\n", "x/mine/msg/Bad.msg, line 1", "must be a number"),
        (
            "x/mine/msg/Loop.msg",
            "int32 a\nLoop[] next\n",
            "x/mine/msg/Loop.msg, line 2",
            "contains itself",
        ),
        (
            "x/Mine/msg/Bad.msg",
            "int32 a\n",
            "x/Mine/msg/Bad.msg",
            "'Mine' is not a ROS package name",
        ),
        ("x/mine/msg/bad.msg", "int32 a\n", "x/mine/msg/bad.msg", "'bad' is not a ROS type name"),
        ("x/mine/Bad.msg", "int32 a\n", "x/mine/Bad.msg", "interface files lie at PACKAGE/msg/"),
    ],
)
def test_bad_definitions_name_the_file_and_line(registry, path, text, where, words):
    """A redefinition of a standard or lab type, a syntax error, an unknown type and the
    like are refused with the file and line."""
    with pytest.raises(InterfaceError) as caught:
        trial_types(registry, {path: text})
    assert str(caught.value).startswith(where + ": "), str(caught.value)
    assert words in str(caught.value)


def test_a_cycle_through_two_files_and_a_type_defined_twice(registry):
    """A type that contains itself through another is refused, as is one defined twice."""
    with pytest.raises(
        InterfaceError,
        match=r"a/msg/B.msg, line 1: a makes a type that contains itself \(a/msg/A -> a/msg/B -> a/msg/A\)",
    ):
        trial_types(registry, {"a/msg/A.msg": "B b\n", "a/msg/B.msg": "A a\n"})
    with pytest.raises(InterfaceError, match=r"a/msg/A is also defined in one/a/msg/A\.msg"):
        trial_types(registry, {"one/a/msg/A.msg": "int8 x\n", "two/a/msg/A.msg": "int8 x\n"})
