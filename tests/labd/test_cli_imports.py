"""The commands that talk to a lab start without the lab's own machinery.

``labd trials`` and the other client commands read the API's bodies (``labd.api.models``)
and the archive's and scheduler's vocabulary; they must not import the simulator, the
trial runner, the index's SQLAlchemy or FastAPI, which take seconds to load. Held here by
what a fresh interpreter has imported, not by timing it (``bench/cli.py`` times it).
"""

from __future__ import annotations

import json
import subprocess
import sys

from labd.cli import COMMANDS

# what the lab itself runs on: a client command imports none of it
LAB = {"mujoco", "dm_control", "labd.sim.base", "scheduler.runner", "sqlalchemy", "fastapi"}
# the commands that talk to a lab, and the modules that define them
CLIENTS = {
    "submit": "remote",
    "trials": "remote",
    "show": "remote",
    "logs": "remote",
    "download": "remote",
    "rerun": "remote",
    "cancel": "remote",
    "tasks": "remote",
    "status": "remote",
    "evaluate": "evaluate",
    "evaluations": "evaluate",
    "reserve": "reserve",
    "export": "export",
}
PROBE = """
import importlib, json, sys
for name in sys.argv[1:]:
    importlib.import_module(name)
print(json.dumps(sorted(sys.modules)))
"""


def loaded(*modules: str) -> set[str]:
    """Every module a fresh interpreter has imported after importing ``modules``."""
    done = subprocess.run(
        [sys.executable, "-c", PROBE, *modules],
        capture_output=True,
        text=True,
        timeout=120,
        check=True,
    )
    return set(json.loads(done.stdout))


def test_the_client_commands_are_the_modules_checked_here():
    """Each command that talks to a lab is defined by the module this file checks for it."""
    assert {name: COMMANDS[name].module for name in CLIENTS} == CLIENTS


def test_client_commands_import_no_simulator_database_web_server_or_numpy():
    """The modules of submit, trials, ..., evaluate, reserve load none of the lab's
    machinery, nor numpy or pyarrow; they do load the API's bodies and its client."""
    modules = [f"labd.commands.{m}" for m in sorted(set(CLIENTS.values()) - {"export"})]
    seen = loaded(*modules)
    assert set(modules) | {"labd.api.models", "scheduler.client", "pydantic", "httpx"} <= seen
    assert (LAB | {"numpy", "pyarrow"}) & seen == set()


def test_export_imports_only_the_formats_readers_besides():
    """``labd export`` reads the export back (pyarrow, numpy), and still none of the lab."""
    seen = loaded("labd.commands.export")
    assert {"labd.commands.export", "repository.formats", "pyarrow"} <= seen
    assert LAB & seen == set()
