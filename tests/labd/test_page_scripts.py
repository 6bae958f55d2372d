"""The pages' own logic, in Node's built-in test runner: ``tests/js/pages/*.test.mjs``
(``node --test``) import the page modules that hold no DOM (the live pages' messages and
commands, the record view's scrubber, the playground's checks, an evaluation's words) and
check them, with the acorn, CodeMirror and three.js that ``web/build.mjs`` serves from
``web/node_modules`` (``make setup``). One pytest case per file, so that ``make test``
runs them and a failure names its file and shows Node's report.

Also here: what the linter cannot see across files, that the pages share their helpers
(``labd/web/static/page.js``) rather than each define its own.
"""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
PAGES = ROOT / "tests" / "js" / "pages"
STATIC = ROOT / "labd" / "web" / "static"
TESTS = sorted(PAGES.glob("*.test.mjs"))


def page_scripts() -> list[Path]:
    return sorted(p for p in STATIC.rglob("*.js") if "vendor" not in p.relative_to(STATIC).parts)


def test_there_are_page_tests() -> None:
    assert len(TESTS) >= 6, TESTS


@pytest.mark.integration
@pytest.mark.skipif(shutil.which("node") is None, reason="needs Node.js")
@pytest.mark.parametrize("script", TESTS, ids=[t.name for t in TESTS])
def test_page_logic_in_node(script: Path) -> None:
    """Every test of the file passes, and it has some (Node's TAP summary)."""
    modules = ROOT / "web" / "node_modules"
    assert modules.is_dir(), f"{modules} is missing: make setup installs it (npm ci in web/)"
    done = subprocess.run(
        ["node", "--test", "--test-reporter=tap", str(script)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    report = done.stdout + done.stderr
    assert done.returncode == 0, report
    counts = dict(re.findall(r"^# (tests|pass|fail) (\d+)$", done.stdout, re.MULTILINE))
    assert int(counts.get("tests", 0)) > 0, report
    assert counts.get("pass") == counts["tests"] and counts.get("fail") == "0", report


def test_helpers_are_defined_once() -> None:
    """``$``, ``el`` and the page's status line live in page.js; a page imports them."""
    own = {
        "$": re.compile(r"^\s*(?:export\s+)?const \$ = ", re.MULTILINE),
        "el": re.compile(r"^\s*(?:export\s+)?function el\(", re.MULTILINE),
        "status": re.compile(r"^\s*(?:export\s+)?function status\(", re.MULTILINE),
    }
    for name, pattern in own.items():
        defined = [p.relative_to(STATIC) for p in page_scripts() if pattern.search(p.read_text())]
        assert defined == [Path("page.js")], f"{name} is defined in {defined}"


def test_the_pages_import_from_this_lab_only() -> None:
    """Every module a page script imports is the lab's own: a path on this server (the
    import maps name ``three`` and ``roslib``), never another host."""
    imported = re.compile(r"""(?:\bfrom\s+|\bimport\s*\(\s*)["']([^"']+)["']""")
    for script in page_scripts():
        for name in imported.findall(script.read_text()):
            assert name.startswith(("/static/", "./", "../")) or name.split("/")[0] in {
                "three",
                "roslib",
            }, f"{script.relative_to(ROOT)} imports {name}"
