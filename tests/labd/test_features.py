"""Each task's export layout: documented entry by entry, and computed from its messages."""

from __future__ import annotations

import re
from pathlib import Path

from labd.sim import registry

DOCS = Path(__file__).resolve().parents[2] / "docs" / "tasks.md"
# the tasks' export layouts; the dm_control pack's and the soccer pack's each follow one
# rule, documented once
LAYOUTS = {name: spec.layout for name in registry.names() if (spec := registry.get(name)).layout}
PACKS = ("dmc-", "soccer-")
BESPOKE = {name: layout for name, layout in LAYOUTS.items() if not name.startswith(PACKS)}


def test_every_task_has_a_layout_and_docs_list_it_in_order():
    """docs/tasks.md lists every entry of every task's layout, in the layout's order, with
    its neutral value; and every registered task has a layout."""
    assert set(LAYOUTS) == set(registry.names())
    text = DOCS.read_text()
    for task, layout in BESPOKE.items():
        section = text[text.index(f"#### `{task}`") :]
        for part, entries in (("observation.state", layout.observation), ("action", layout.action)):
            table = section[section.index(f"`{part}` (") :]
            rows = re.findall(r"^\| (\d+) \| `([^`]+)` \|.*\| (-?[\d.e+-]+) \|$", table, re.M)
            listed = [(int(i), name, float(n)) for i, name, n in rows[: len(entries)]]
            assert listed == [(i, e.name, e.neutral) for i, e in enumerate(entries)]


def test_command_entries_only_read_command_topics():
    """Actions come from the task's command topics, observations from its observations."""
    for task, layout in LAYOUTS.items():
        observations, commands = registry.get(task).topics()
        assert {t for e in layout.action for t in e.topics} <= set(commands)
        assert {t for e in layout.observation for t in e.topics} <= set(observations)
        names = [e.name for e in (*layout.observation, *layout.action)]
        assert len(names) == len(set(names))
