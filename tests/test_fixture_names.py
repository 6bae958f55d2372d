"""Fixtures are named for what they hold (README.md, "Fixtures' names"), and each is defined
once: no function under tests/ is called ``lab`` again (it meant a process, a thread, a
tuple and a config builder), and no fixture is pasted into a second file (one that
several files use as it is lives in their nearest conftest.py)."""

from __future__ import annotations

import ast
import textwrap
from collections import defaultdict
from collections.abc import Iterator
from pathlib import Path

TESTS = Path(__file__).resolve().parent
BANNED = "lab"
HINT = 'name it for what it holds (README.md, "Fixtures\' names")'


def is_fixture(decorator: ast.expr) -> bool:
    target = decorator.func if isinstance(decorator, ast.Call) else decorator
    return (isinstance(target, ast.Attribute) and target.attr == "fixture") or (
        isinstance(target, ast.Name) and target.id == "fixture"
    )


def fixture_name(function: ast.FunctionDef | ast.AsyncFunctionDef) -> str | None:
    """The name tests ask for (``@pytest.fixture(name=...)`` or the function's); None for a
    function that is no fixture."""
    for decorator in function.decorator_list:
        if is_fixture(decorator):
            if isinstance(decorator, ast.Call):
                for keyword in decorator.keywords:
                    if keyword.arg == "name" and isinstance(keyword.value, ast.Constant):
                        return str(keyword.value.value)
            return function.name
    return None


def module_names(tree: ast.Module) -> dict[str, ast.stmt]:
    """The statement that makes each module-level name of a file: its definition, its
    assignment or its import."""
    names: dict[str, ast.stmt] = {}
    for statement in tree.body:
        if isinstance(statement, ast.Import | ast.ImportFrom):
            for alias in statement.names:
                names[alias.asname or alias.name.split(".")[0]] = statement
        elif isinstance(statement, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef):
            names[statement.name] = statement
        elif isinstance(statement, ast.Assign | ast.AnnAssign):
            targets = statement.targets if isinstance(statement, ast.Assign) else [statement.target]
            for target in targets:
                for node in ast.walk(target):
                    if isinstance(node, ast.Name):
                        names[node.id] = statement
    return names


def meaning(function: ast.FunctionDef | ast.AsyncFunctionDef, names: dict[str, ast.stmt]) -> str:
    """The fixture's decorators, arguments and body (its docstring left out), and what each
    module-level name they read is, followed through those names' own definitions: two
    fixtures mean the same only if they would do the same (``Simulation(TASK)`` in two
    files whose ``TASK`` differs do not)."""
    body = function.body
    if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant):
        body = body[1:]
    parts = [ast.dump(d) for d in function.decorator_list] + [ast.dump(function.args)]
    parts += [ast.dump(statement) for statement in body]
    own = {a.arg for a in ast.walk(function.args) if isinstance(a, ast.arg)}
    own |= {
        n.id
        for n in ast.walk(function)
        if isinstance(n, ast.Name) and not isinstance(n.ctx, ast.Load)
    }
    read: dict[str, str] = {}
    pending: list[ast.AST] = [*function.decorator_list, function.args, *body]
    while pending:
        for node in ast.walk(pending.pop()):
            if isinstance(node, ast.Name) and node.id in names.keys() - own - read.keys():
                made = names[node.id]
                if isinstance(made, ast.Import | ast.ImportFrom):  # where from, not what else
                    source = made.module if isinstance(made, ast.ImportFrom) else ""
                    read[node.id] = f"imported from {source}"
                else:
                    read[node.id] = ast.dump(made)
                    pending.append(made)
    parts += [f"{name}: {read[name]}" for name in sorted(read)]
    return "\n".join(parts)


def python_files(root: Path) -> Iterator[Path]:
    for path in sorted(root.rglob("*.py")):
        if "node_modules" not in path.relative_to(root).parts:  # npm's packages
            yield path


def fixture_problems(root: Path) -> list[str]:
    """What is wrong with the fixtures under ``root``, one sentence each."""
    problems: list[str] = []
    files_by_meaning: dict[tuple[str, str], set[str]] = defaultdict(set)
    for path in python_files(root):
        tree = ast.parse(path.read_text(), str(path))
        names = module_names(tree)
        where = path.relative_to(root)
        for node in ast.walk(tree):
            if not isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                continue
            name = fixture_name(node)
            if BANNED in (name, node.name):
                kind = "a fixture" if name is not None else "a function"
                problems.append(f"{where}:{node.lineno}: {kind} called {BANNED!r}; {HINT}")
            if name is not None:
                files_by_meaning[(name, meaning(node, names))].add(str(where))
    for (name, _), found in sorted(files_by_meaning.items()):
        files = sorted(found)
        if len(files) > 1:
            problems.append(
                f"the fixture {name!r} is defined the same in {', '.join(files)}: define it"
                " once, in their nearest conftest.py"
            )
    return problems


def write(root: Path, files: dict[str, str]) -> Path:
    for name, text in files.items():
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        (root / name).write_text(textwrap.dedent(text))
    return root


def test_the_tests_fixtures_are_named_for_what_they_hold_and_defined_once():
    """No function under tests/ is called ``lab`` and no fixture is defined the same in two
    files."""
    assert fixture_problems(TESTS) == []


def test_a_fixture_or_a_helper_called_lab_is_named(tmp_path):
    """A bare ``lab``, as a fixture (by its function's name or ``name=``) or as a helper,
    is reported with its file and line."""
    write(
        tmp_path,
        {
            "a/test_one.py": """\
                import pytest

                @pytest.fixture
                def lab(tmp_path):
                    return tmp_path
                """,
            "b/test_two.py": """\
                import pytest

                @pytest.fixture(name="lab")
                def the_lab():
                    return 1

                def lab(*argv):
                    return argv
                """,
        },
    )
    assert fixture_problems(tmp_path) == [
        f"a/test_one.py:4: a fixture called 'lab'; {HINT}",
        f"b/test_two.py:4: a fixture called 'lab'; {HINT}",
        f"b/test_two.py:7: a function called 'lab'; {HINT}",
    ]


def test_a_fixture_pasted_into_another_file_is_reported_naming_both(tmp_path):
    """Two files that define a fixture of one name with the same code and module-level
    names, their docstrings aside, are reported together."""
    fixture = '''\
        import pytest
        from repository.index import Index

        START = 1_000_000.0

        @pytest.fixture
        def index(database_url):
            """{doc}"""
            index = Index.open(database_url)
            index.now = START
            yield index
            index.close()
        '''
    write(
        tmp_path,
        {
            "repository/test_index.py": fixture.format(doc="The index."),
            "scheduler/test_queue.py": fixture.format(doc="An empty index on each database."),
        },
    )
    assert fixture_problems(tmp_path) == [
        "the fixture 'index' is defined the same in repository/test_index.py,"
        " scheduler/test_queue.py: define it once, in their nearest conftest.py"
    ]


def test_fixtures_alike_in_code_but_not_in_what_they_do_are_left_alone(tmp_path):
    """Fixtures of one name whose module-level names differ (another task, another clock)
    or whose scope differs are different fixtures, not copies."""
    sim = """\
        import pytest

        TASK = "{task}"

        class Clock:
            def __init__(self):
                self.now = {now}

        @pytest.fixture(scope="{scope}")
        def sim():
            return Simulation(TASK, seed=3)

        @pytest.fixture
        def clock():
            return Clock()
        """
    write(
        tmp_path,
        {
            "test_icreate.py": sim.format(task="icreate-maze", now=1.0, scope="function"),
            "test_pr2.py": sim.format(task="pr2-table", now=2.0, scope="function"),
            "test_maze_again.py": sim.format(task="icreate-maze", now=3.0, scope="module"),
        },
    )
    assert fixture_problems(tmp_path) == []
