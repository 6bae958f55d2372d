"""The pack's export layouts: one entry per observation number and per action value.

Every pack task follows one rule (docs/tasks.md, "Exports"): ``observation.state`` is
the suite's observation, key by key in the suite's order, each key's array flattened in
C order (``position.0``, ``position.1``, ...; a scalar key is one entry named by the
key); ``action`` is the ``/action`` vector (``0``, ``1``, ..., one per actuator in the
action spec's order). Before any ``/action`` the action entries are 0, the neutral
action. The camera is the suite's camera 0, as ``/camera/image/compressed``.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

from labd.sim.dmc.catalog import CATALOG, Listing
from labd.sim.dmc.task import ACTION, CAMERA_IMAGE, OBSERVATION
from repository.export import Camera, Entry, Extract, Layout, Messages

if TYPE_CHECKING:
    from labd.sim.registry import TaskSpec

VERSION = "1"
CAMERA = Camera("camera", CAMERA_IMAGE)


def _element(i: int) -> Extract:
    """Element ``i`` of a Float64MultiArray's data."""

    def extract(messages: Messages, topic: str) -> float | None:
        return float(messages[topic].data[i])

    return extract


def _observation_entries(listing: Listing) -> tuple[Entry, ...]:
    entries = []
    for key, shape in listing.observations:
        topic = OBSERVATION + key
        for i in range(math.prod(shape)):
            name = f"{key}.{i}" if shape else key
            doc = f"element {i} of the suite's observation {key!r}, flattened"
            entries.append(Entry(name, (topic,), _element(i), 0.0, "", doc))
    return tuple(entries)


def _action_entries(listing: Listing) -> tuple[Entry, ...]:
    return tuple(
        Entry(str(i), (ACTION,), _element(i), 0.0, "", f"the control of the actuator {name!r}")
        for i, name in enumerate(listing.actuators)
    )


def layout_of(listing: Listing) -> Layout:
    """The export layout of one pack task."""
    return Layout(
        task=listing.name,
        version=VERSION,
        observation=_observation_entries(listing),
        action=_action_entries(listing),
        cameras=(CAMERA,),
        instruction=lambda _messages: listing.goal,
    )


LAYOUTS = {listing.name: layout_of(listing) for listing in CATALOG}


def layout(spec: TaskSpec) -> Layout:
    """The export layout of a pack task's spec (KeyError for a task not of the pack)."""
    return LAYOUTS[spec.name]
