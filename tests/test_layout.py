"""The package boundaries of DESIGN.md, checked on the source."""

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
    "scheduler": {"labd", "repository", "sandbox"},
    "labd": {"scheduler", "repository", "sandbox"},
}


def imported_packages(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(), str(path))
    names: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(alias.name.split(".")[0] for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(node.module.split(".")[0])
    return names


@pytest.mark.parametrize("package", sorted(ALLOWED))
def test_packages_import_only_what_the_design_allows(package):
    """Each package imports only the packages of ours that DESIGN.md lets it depend on."""
    offenders = {}
    for path in (ROOT / package).rglob("*.py"):
        wrong = (imported_packages(path) & OURS) - ALLOWED[package] - {package}
        if wrong:
            offenders[str(path.relative_to(ROOT))] = sorted(wrong)
    assert offenders == {}


def test_every_package_is_typed():
    """Each package ships py.typed, so users' type checkers read its annotations."""
    assert all((ROOT / package / "py.typed").exists() for package in OURS)
