"""The soccer pack's export layouts: the home side's view, one entry per number.

One rule for every team size (docs/tasks.md, "Soccer"): ``observation.state`` is each
home player's observation in turn, key by key in dm_control's order, each key's array
flattened in C order (``player_0.ball_ego_position.0``, ...; a scalar key is one entry
named by the key); ``action`` is each home player's three values (``player_0.roll``,
``player_0.steer``, ``player_0.kick``), 0 before any command. What a learner learns
from a lone trial is to play home; the away side's topics stay in the record. The
camera is the pitch from above.
"""

from __future__ import annotations

import math

from labd.sim.soccer.task import ACTUATORS, CAMERA_IMAGE, observation_keys, player
from repository.export import Camera, Entry, Extract, Layout, Messages

VERSION = "1"
CAMERA = Camera("top_down", CAMERA_IMAGE)
HOME = "home"


def _element(i: int) -> Extract:
    """Element ``i`` of a Float64MultiArray's data."""

    def extract(messages: Messages, topic: str) -> float | None:
        return float(messages[topic].data[i])

    return extract


def layout_of(name: str, team_size: int) -> Layout:
    """The export layout of the pack's task ``name``."""
    observation = []
    action = []
    for p in range(team_size):
        prefix = player(HOME, p)
        for key, shape in observation_keys(team_size):
            topic = f"{prefix}observation/{key}"
            for i in range(math.prod(shape)):
                entry = f"player_{p}.{key}.{i}" if shape else f"player_{p}.{key}"
                doc = f"element {i} of home's player {p}'s {key!r}, flattened"
                observation.append(Entry(entry, (topic,), _element(i), 0.0, "", doc))
        action += [
            Entry(
                f"player_{p}.{name}",
                (prefix + "action",),
                _element(k),
                0.0,
                "",
                f"home's player {p}'s {name}, in [-1, 1]",
            )
            for k, name in enumerate(ACTUATORS)
        ]
    return Layout(
        task=name,
        version=VERSION,
        observation=tuple(observation),
        action=tuple(action),
        cameras=(CAMERA,),
        instruction=lambda _messages: "score a goal: put the ball in the opponents' goal",
    )
