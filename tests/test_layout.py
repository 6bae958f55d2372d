"""The package boundaries of DESIGN.md, checked on the source: imports follow the data flow.

    repo URL → scheduler → sandbox → bridge ⇄ sim → recorder → repository → API

``repository`` and ``sandbox`` import nothing of ours; ``controllers`` runs in the sandbox
and imports nothing of ours; ``scheduler`` uses ``sandbox``, ``repository`` and the
trial protocol it defines itself (``scheduler.host``), which ``labd`` implements: never
``labd``. Inside ``labd``, each layer imports only layers below it, and the robots, the
bridge and the recorder, siblings on the graph, never import each other.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
OURS = {"labd", "scheduler", "repository", "sandbox", "controllers"}
# package -> the packages of ours it may import
ALLOWED = {
    "controllers": set(),  # runs inside the sandbox: standard library and websockets only
    "sandbox": set(),
    "repository": set(),
    "scheduler": {"repository", "sandbox"},
    "labd": {"scheduler", "repository", "sandbox"},
}
# labd's layers, bottom first: a module may import its own layer's package and lower ones.
LAYERS = [
    {"labd.errors", "labd.clock", "labd.config", "labd.offload", "labd"},
    {"labd.graph"},
    {"labd.sim", "labd.bridge", "labd.recorder"},
    {"labd.station", "labd.recorded"},
    {
        "labd.trial",
        "labd.match",
        "labd.replay",
        "labd.live",
        "labd.exports",
        "labd.scripted",
        "labd.gym",
    },
    {
        "labd.service",
        "labd.authorizer",
        "labd.videos",
        "labd.replays",
        "labd.cluster",
        "labd.workers",
        "labd.hosted",
        "labd.playground",
        "labd.health",
        "labd.metrics",
    },
    {"labd.api"},
    {"labd.web"},
    {"labd.lab", "labd.privacy"},
    {"labd.commands", "labd.cli", "labd.__main__"},
]
SIBLINGS = {"labd.sim", "labd.bridge", "labd.recorder"}  # on the graph, apart


def imports(path: Path) -> set[str]:
    """The absolute module names ``path`` imports (``from a.b import c`` gives ``a.b``)."""
    tree = ast.parse(path.read_text(), str(path))
    names: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(node.module)
    return names


def unit(module: str) -> str:
    """The layer unit of a labd module: ``labd.bridge.ops.topics`` → ``labd.bridge``."""
    parts = module.split(".")
    candidate = ".".join(parts[:2])
    return candidate if any(candidate in layer for layer in LAYERS) else "labd"


def layer(module: str) -> int:
    name = unit(module)
    return next(i for i, members in enumerate(LAYERS) if name in members)


def module_name(path: Path) -> str:
    relative = path.relative_to(ROOT).with_suffix("")
    parts = list(relative.parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


@pytest.mark.parametrize("package", sorted(ALLOWED))
def test_packages_import_only_what_the_design_allows(package):
    """Each package imports only the packages of ours that DESIGN.md lets it depend on."""
    offenders = {}
    for path in (ROOT / package).rglob("*.py"):
        tops = {name.split(".")[0] for name in imports(path)}
        wrong = (tops & OURS) - ALLOWED[package] - {package}
        if wrong:
            offenders[str(path.relative_to(ROOT))] = sorted(wrong)
    assert offenders == {}


def test_labd_layers_never_import_upward():
    """Inside labd, no module imports a layer above its own, nor a sibling on its layer."""
    offenders = {}
    for path in (ROOT / "labd").rglob("*.py"):
        me = module_name(path)
        mine = layer(me)
        wrong = []
        for name in imports(path):
            if not name.startswith("labd"):
                continue
            theirs = layer(name)
            apart = {unit(name), unit(me)} <= SIBLINGS and unit(name) != unit(me)
            if theirs > mine or apart:
                wrong.append(name)
        if wrong:
            offenders[str(path.relative_to(ROOT))] = sorted(wrong)
    assert offenders == {}


def test_the_layer_rule_catches_an_upward_import(tmp_path):
    """The rule above is not vacuous: a recorder importing the bridge is caught."""
    assert layer("labd.recorder.record") == layer("labd.bridge.server")
    assert unit("labd.recorder.record") != unit("labd.bridge.server")
    assert layer("labd.graph.graph") < layer("labd.api.app")
    bad = tmp_path / "bad.py"
    bad.write_text("from labd.bridge.server import BridgeServer\nimport scheduler.runner\n")
    assert imports(bad) == {"labd.bridge.server", "scheduler.runner"}


def test_every_package_is_typed():
    """Each package ships py.typed, so users' type checkers read its annotations."""
    assert all((ROOT / package / "py.typed").exists() for package in OURS)
