"""The type registry: rosbags' messages, the kept services and actions, and their names."""

from __future__ import annotations

import pytest

from labd.graph.types import TypeRegistry


@pytest.mark.parametrize(
    ("kind", "name", "fields"),
    [
        ("service", "example_interfaces/srv/AddTwoInts", (["a", "b"], ["sum"])),
        ("service", "turtlesim/srv/Spawn", (["x", "y", "theta", "name"], ["name"])),
        ("service", "turtlesim_msgs/srv/TeleportRelative", (["linear", "angular"], [])),
        (
            "service",
            "action_msgs/srv/CancelGoal",
            (["goal_info"], ["return_code", "goals_canceling"]),
        ),
        (
            "action",
            "action_tutorials_interfaces/action/Fibonacci",
            (["order"], ["partial_sequence"]),
        ),
        ("action", "example_interfaces/Fibonacci", (["order"], ["sequence"])),
        ("action", "turtlesim/action/RotateAbsolute", (["theta"], ["remaining"])),
    ],
)
def test_tutorial_interfaces_are_known(registry: TypeRegistry, kind, name, fields):
    """The interfaces of the ROS 2 tutorials and client test suites resolve, with their fields."""
    if kind == "service":
        service = registry.service(name)
        parts = (service.request, service.response)
    else:
        action = registry.action(name)
        parts = (action.goal, action.feedback)
    names = tuple([f.name for f in p.fields if not f.name.startswith("structure_")] for p in parts)
    assert names == fields


def test_tutorial_messages_are_known(registry: TypeRegistry):
    """example_interfaces' and turtlesim's messages resolve in both spellings."""
    assert [f.name for f in registry.message("turtlesim/Pose").fields] == [
        "x",
        "y",
        "theta",
        "linear_velocity",
        "angular_velocity",
    ]
    assert registry.message("example_interfaces/msg/Int64").fields[0].base == "int64"
    assert "example_interfaces/msg/String" in set(registry.message_names())


def test_the_shared_registry_is_made_once_and_is_the_labs_own_types():
    shared = TypeRegistry.shared()
    assert TypeRegistry.shared() is shared
    assert shared.standard and TypeRegistry.default().typestore is not shared.typestore
    assert shared.message("nav_msgs/msg/Odometry").name == "nav_msgs/msg/Odometry"
