"""docs/architecture.md draws a trial's way from the request to the record; the code is it.

The drawings are fenced blocks of three kinds, held to the code here as
tests/faults/test_documented_limits.py holds the documented limits:

- every dotted name drawn (``scheduler.queue.Queue.submit``) imports;
- a call tree (``A ─▶ B``: A calls B) draws only calls A makes: A's body names B, or A
  asks the route that B answers; its branches are drawn whole (``│`` from a caller down
  to each of its callees), and a route written beside a function is one it answers;
- a field tree lists its class's fields in their order, each part of another class by
  name with its fields in braces (or drawn as a tree of its own);
- the mapping ``Order → TrialSetup → Manifest`` says where every field of an Order and of
  a setup goes, and where every argument of ``Manifest.trial`` comes from.

And every function of the lab that makes an Order or a Manifest, or reads one from a
record, is drawn making it. So a field added, a function renamed or a call moved fails
here until the drawing says so.
"""

from __future__ import annotations

import ast
import dataclasses
import importlib
import inspect
import re
import sys
import textwrap
import types
import typing
from collections.abc import Iterator
from dataclasses import dataclass
from itertools import pairwise
from pathlib import Path
from typing import Any

import pytest
from fastapi import APIRouter
from pydantic import BaseModel

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "architecture.md"
PACKAGES = ("labd", "scheduler", "repository", "sandbox", "controllers")
DOTTED = re.compile(rf"(?<![\w./-])(?:{'|'.join(PACKAGES)})(?:\.\w+)+")
ROUTE = re.compile(r"\b(GET|POST|PUT|PATCH|DELETE) (/[^\s,:;)]*)")
CALL = "─▶"
BECOMES = "→"
FIELD = re.compile(r"[├└]── ")
TREE_CHARS = frozenset(" │├└─▶")
# What makes or reads the two values, as the code spells the call.
MAKERS = {
    ("Order", None): "repository.trial.Order",
    ("Manifest", "trial"): "repository.manifest.Manifest.trial",
    ("Manifest", "drive"): "repository.manifest.Manifest.drive",
    ("Manifest", "from_json"): "repository.manifest.Manifest.from_json",
}


@dataclass(frozen=True)
class Block:
    line: int  # of its first line in the doc
    lines: list[str]

    def where(self, index: int) -> str:
        return f"architecture.md:{self.line + index}"


def blocks() -> list[Block]:
    found, current, start = [], None, 0
    for number, text in enumerate(DOC.read_text().splitlines(), 1):
        if text.startswith("```"):
            if current is None:
                current, start = [], number + 1
            else:
                found.append(Block(start, current))
                current = None
        elif current is not None:
            current.append(text)
    return found


BLOCKS = blocks()
CALL_TREES = [b for b in BLOCKS if any(CALL in line for line in b.lines)]
FIELD_TREES = [b for b in BLOCKS if any(FIELD.search(line) for line in b.lines)]
MAPPINGS = [b for b in BLOCKS if any(BECOMES in line for line in b.lines)]


def resolve(name: str) -> Any:
    """The object ``name`` names: its longest importable module, then attributes."""
    parts = name.split(".")
    for cut in range(len(parts), 0, -1):
        module_name = ".".join(parts[:cut])
        try:
            found: Any = importlib.import_module(module_name)
        except ModuleNotFoundError as err:
            if err.name is None or not (module_name + ".").startswith(err.name + "."):
                raise  # the module is there; something it imports is not
            continue
        for n, attr in enumerate(parts[cut:], cut):
            if not hasattr(found, attr):
                pytest.fail(f"{name}: {'.'.join(parts[:n])} has no {attr}")
            found = getattr(found, attr)
        return found
    pytest.fail(f"{name}: no such module")


def named(obj: Any) -> set[str]:
    """Every name and attribute the body of ``obj`` (a function, method, property or
    class) refers to: what it may call."""
    if isinstance(obj, property):
        obj = obj.fget
    tree = ast.parse(textwrap.dedent(inspect.getsource(inspect.unwrap(obj))))
    definition = tree.body[0]
    assert isinstance(definition, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef)
    names = set()
    for statement in definition.body:
        for node in ast.walk(statement):
            if isinstance(node, ast.Name):
                names.add(node.id)
            elif isinstance(node, ast.Attribute):
                names.add(node.attr)
    return names


def routes(obj: Any) -> set[tuple[str, str]]:
    """The (method, path) pairs ``obj`` answers, on any router of its module."""
    module = sys.modules.get(getattr(obj, "__module__", ""), None)
    found = set()
    for router in vars(module).values() if module else ():
        if isinstance(router, APIRouter):
            for route in router.routes:
                if getattr(route, "endpoint", None) is obj:
                    found |= {(method, route.path) for method in route.methods}
    return found


def asks(caller: Any, path: str) -> bool:
    """Whether ``caller``'s source asks the route ``path`` (its parameters any value)."""
    pattern = "".join(
        r"\{[^}]*\}" if part.startswith("{") else re.escape(part)
        for part in re.split(r"(\{[^}]*\})", path)
    )
    source = inspect.getsource(caller.fget if isinstance(caller, property) else caller)
    return re.search(rf"[\"']{pattern}[\"']", source) is not None


@dataclass(frozen=True)
class Edge:
    caller: str
    callee: str
    where: str


@dataclass(frozen=True)
class Node:
    index: int
    column: int
    name: str


def call_tree(block: Block, problems: list[str]) -> Iterator[Edge]:
    """The arrows of a call tree: ``A ─▶ B`` on a line, and each ``├─▶``/``└─▶`` from
    the function drawn above it whose branch it hangs on (a branch drawn broken is one
    of ``problems``). A line's first name is a node only when nothing but the tree's
    lines stand before it; names in what is said beside it are only resolved."""
    nodes: list[Node] = []
    for index, text in enumerate(block.lines):
        found = list(DOTTED.finditer(text))
        if not found:
            continue
        first, prefix = found[0], text[: found[0].start()]
        if not set(prefix) <= TREE_CHARS:
            continue
        chain = [first]
        for match in found[1:]:
            if text[chain[-1].end() : match.start()].strip() != CALL:
                break
            chain.append(match)
        for a, b in pairwise(chain):
            yield Edge(a.group(), b.group(), block.where(index))
        if prefix.strip():
            column = max(prefix.rfind("├"), prefix.rfind("└"))
            parent = next((n for n in reversed(nodes) if n.column <= column), None)
            if not prefix.rstrip().endswith(CALL) or column < 0 or parent is None:
                problems.append(f"{block.where(index)}: an arrow from nowhere: {text!r}")
                continue
            broken = [
                between
                for between in range(parent.index + 1, index)
                if block.lines[between][column : column + 1] not in ("│", "├")
            ]
            if broken:
                problems.append(
                    f"{block.where(broken[0])}: the branch from {parent.name} to"
                    f" {first.group()} is broken here (column {column + 1})"
                )
            yield Edge(parent.name, first.group(), block.where(index))
        nodes.append(Node(index, first.start(), first.group()))


PROBLEMS: list[str] = []
EDGES = [edge for block in CALL_TREES for edge in call_tree(block, PROBLEMS)]
NAMES = sorted({m.group() for b in BLOCKS for line in b.lines for m in DOTTED.finditer(line)})


def test_the_drawings_are_there():
    """The section draws the call trees (each branch whole), the Order's and the
    Manifest's fields, and the mapping between them (so the tests below have something
    to hold)."""
    assert len(EDGES) >= 50
    assert not PROBLEMS, "\n".join(PROBLEMS)
    roots = {b.lines[0].split()[0] for b in FIELD_TREES}
    assert {"repository.trial.Order", "repository.manifest.Manifest"} <= roots
    assert len(MAPPINGS) == 1


@pytest.mark.parametrize("name", NAMES)
def test_every_name_drawn_imports(name):
    """A dotted name in a drawing is a module, class, function or attribute of the code."""
    resolve(name)


@pytest.mark.parametrize("edge", EDGES, ids=lambda e: f"{e.caller}->{e.callee}")
def test_every_arrow_is_a_call(edge):
    """``A ─▶ B``: A's body names B, or A asks the route B answers."""
    caller, callee = resolve(edge.caller), resolve(edge.callee)
    last = edge.callee.rsplit(".", 1)[1]
    held = last in named(caller) or any(asks(caller, path) for _, path in routes(callee))
    assert held, f"{edge.where}: {edge.caller} does not call {edge.callee}"


def test_every_route_written_is_its_functions():
    """``POST /api/trials`` beside a function: that function answers it."""
    checked = 0
    for block in CALL_TREES:
        for index, text in enumerate(block.lines):
            found = DOTTED.search(text)
            for method, path in ROUTE.findall(text):
                assert found, f"{block.where(index)}: {method} {path} beside no function"
                answers = routes(resolve(found.group()))
                assert (method, path) in answers, (
                    f"{block.where(index)}: {found.group()} answers {sorted(answers)},"
                    f" not {method} {path}"
                )
                checked += 1
    assert checked >= 7


# -- the fields -------------------------------------------------------------------------


def fields(cls: type) -> list[tuple[str, Any]]:
    """A pydantic model's or a dataclass's fields, in order, with their types."""
    if issubclass(cls, BaseModel):
        return [(name, info.annotation) for name, info in cls.model_fields.items()]
    assert dataclasses.is_dataclass(cls), f"{cls} is neither a model nor a dataclass"
    hints = typing.get_type_hints(cls)
    return [(f.name, hints[f.name]) for f in dataclasses.fields(cls)]


def parts(annotation: Any) -> set[type]:
    """The models and dataclasses a field's type holds (``tuple[Pinned, ...]``: Pinned)."""
    if isinstance(annotation, type) and (
        issubclass(annotation, BaseModel) or dataclasses.is_dataclass(annotation)
    ):
        return {annotation}
    found: set[type] = set()
    if isinstance(annotation, types.UnionType) or typing.get_origin(annotation) is not None:
        for arg in typing.get_args(annotation):
            found |= parts(arg)
    return found


@dataclass
class Drawn:
    name: str
    part: str | None  # the class named beside it
    listed: list[str] | None  # that class's fields, in braces
    where: str


def field_tree(block: Block) -> tuple[str, list[Drawn]]:
    """The class a field tree draws, and its items."""
    root = block.lines[0].split()[0]
    items: list[Drawn] = []
    column = None
    pending: list[str] | None = None
    for index, text in enumerate(block.lines[1:], 1):
        if pending is not None:  # the braces go on
            pending.append(text.strip(" │"))
            if "}" in text:
                items[-1].listed = _listed(" ".join(pending))
                pending = None
            continue
        match = re.match(r"^([ │]*)[├└]── (\w+)(?::\s*(\S+))?", text)
        if match is None:
            continue
        where = block.where(index)
        assert column in (None, len(match.group(1))), f"{where}: nested parts go in braces"
        column = len(match.group(1))
        items.append(Drawn(match.group(2), match.group(3), None, where))
        if "{" in text:
            rest = text[text.index("{") :]
            if "}" in rest:
                items[-1].listed = _listed(rest)
            else:
                pending = [rest]
    assert pending is None, f"{block.where(0)}: braces left open"
    return root, items


def _listed(text: str) -> list[str]:
    inside = text[text.index("{") + 1 : text.index("}")]
    return [name.strip() for name in inside.split(",") if name.strip()]


TREES = dict(field_tree(b) for b in FIELD_TREES)


@pytest.mark.parametrize("root", sorted(TREES))
def test_every_field_tree_is_its_class(root):
    """A field tree lists its class's fields in order; each part of another class names
    that class, and lists its fields in order (or it is drawn as a tree of its own)."""
    cls = resolve(root)
    items = TREES[root]
    actual = fields(cls)
    assert [i.name for i in items] == [name for name, _ in actual], (
        f"{root}: the drawing lists {[i.name for i in items]}, the code {[n for n, _ in actual]}"
    )
    for item, (name, annotation) in zip(items, actual, strict=True):
        held = parts(annotation)
        if not held:
            assert item.part is None, f"{item.where}: {root}.{name} holds no {item.part}"
            continue
        assert item.part is not None, (
            f"{item.where}: {root}.{name} holds a {', '.join(c.__name__ for c in held)}:"
            " draw its fields"
        )
        part = resolve(item.part)
        assert held == {part}, f"{item.where}: {root}.{name} holds {held}, not {item.part}"
        if item.listed is None:
            assert item.part in TREES, f"{item.where}: {item.part}'s fields are drawn nowhere"
            continue
        assert item.listed == [n for n, _ in fields(part)], (
            f"{item.where}: {item.part} has the fields {[n for n, _ in fields(part)]}"
        )
        for inner, inner_type in fields(part):  # a part of a part: drawn as its own tree
            for deeper in parts(inner_type):
                drawn = f"{deeper.__module__}.{deeper.__qualname__}"
                assert drawn in TREES, f"{item.where}: {item.part}.{inner}'s {drawn} is not drawn"


# -- the mapping ------------------------------------------------------------------------


def mapping(block: Block) -> tuple[list[str], list[set[str]]]:
    """The classes in the mapping's head, and the fields drawn in each one's column."""
    head = block.lines[0]
    classes = list(DOTTED.finditer(head))
    starts = [m.start() for m in classes]
    columns: list[set[str]] = [set() for _ in classes]
    for text in block.lines[1:]:
        at = 0
        for n, segment in enumerate(text.split(BECOMES)):
            begin = at + len(segment) - len(segment.lstrip())
            at += len(segment) + len(BECOMES)
            if not segment.strip() or (n == 0 and begin > 0):
                continue
            column = max(i for i, start in enumerate(starts) if start <= begin)
            listed = re.match(r"\s*(\w+(?:\s*,\s*\w+)*)", segment)
            if listed:
                columns[column] |= {name.strip() for name in listed.group(1).split(",")}
    return [m.group() for m in classes], columns


def test_the_mapping_says_where_every_field_goes():
    """Every field of an Order and of a TrialSetup is drawn in its column (so a new one
    says where it goes), and every argument of ``Manifest.trial`` is drawn coming from
    somewhere."""
    [block] = MAPPINGS
    names, columns = mapping(block)
    assert names == [
        "repository.trial.Order",
        "scheduler.host.TrialSetup",
        "repository.manifest.Manifest",
    ]
    order, setup, manifest = (resolve(name) for name in names)
    assert columns[0] == {n for n, _ in fields(order)}, "an Order's fields, each drawn once"
    assert columns[1] == {n for n, _ in fields(setup)}, "a TrialSetup's fields, each drawn once"
    made = set(inspect.signature(manifest.trial).parameters)
    assert made <= columns[2] <= {n for n, _ in fields(manifest)}, (
        f"Manifest.trial takes {sorted(made)}; the drawing has {sorted(columns[2])}"
    )


# -- what makes and reads the two values ------------------------------------------------


def makers() -> Iterator[tuple[str, str]]:
    """(the function, what it makes or reads) for every call that makes an Order or a
    Manifest, or reads one, in the lab's packages."""
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            module = ".".join(path.relative_to(ROOT).with_suffix("").parts)
            module = module.removesuffix(".__init__")
            yield from _makers(ast.parse(path.read_text()), module)


def _makers(tree: ast.Module, module: str) -> Iterator[tuple[str, str]]:
    """A call belongs to the module's function or the class's method it is in (and a
    function nested in either, to that one)."""

    def visit(node: ast.AST, scope: list[str], inside: bool) -> Iterator[tuple[str, str]]:
        for child in ast.iter_child_nodes(node):
            inner, done = scope, inside
            if not inside and isinstance(child, ast.ClassDef):
                inner = [*scope, child.name]
            elif not inside and isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef):
                inner, done = [*scope, child.name], True
            if isinstance(child, ast.Call) and inside:
                func = child.func
                key = None
                if isinstance(func, ast.Name):
                    key = (func.id, None)
                elif isinstance(func, ast.Attribute) and isinstance(func.value, ast.Name):
                    key = (func.value.id, func.attr)
                if key in MAKERS:
                    yield ".".join([module, *scope]), MAKERS[key]
            yield from visit(child, inner, done)

    yield from visit(tree, [], False)


MADE = sorted(set(makers()))


def test_the_makers_are_found():
    """The search below finds the calls it looks for (Submissions.prepare makes an Order)."""
    assert ("scheduler.submit.Submissions.prepare", "repository.trial.Order") in MADE
    assert len(MADE) >= 10


@pytest.mark.parametrize("maker", MADE, ids=lambda m: f"{m[0]}->{m[1]}")
def test_every_maker_is_drawn(maker):
    """A function that makes an Order or a Manifest, or reads one from a record, is drawn
    with that arrow (or the class whose method it is)."""
    function, made = maker
    drawn = {(e.caller, e.callee) for e in EDGES}
    owner = function.rsplit(".", 1)[0]
    assert (function, made) in drawn or (owner, made) in drawn, (
        f"{function} calls {made}: draw it in docs/architecture.md"
    )
