"""The playground's scripts and API in process: Node's parse errors at their line, the
files a script is committed as, each task's starting script, and the API's refusals
(nothing is committed for a script that does not parse). A script that becomes a trial,
through the lab's own git server, is tested in tests/integration/test_playground_browser.py.
"""

# ruff: noqa: F811 (the API's fixtures, imported from test_api, are the tests' arguments)
from __future__ import annotations

import json
import shutil

import pytest

from labd import playground
from labd.commands import serve
from labd.playground import NoNode, PlaygroundError, Script, ScriptError, check, files
from labd.sim import registry
from repository.index import Filters
from scheduler import controller
from tests.labd.test_api import api, auth, service, token  # noqa: F401 (fixtures)

NODE = shutil.which("node")
needs_node = pytest.mark.skipif(NODE is None, reason="no Node.js on this machine")


@needs_node
@pytest.mark.parametrize(
    ("text", "line", "column", "said"),
    [
        ("let x = ;\n", 1, 9, "SyntaxError: Unexpected token ';'"),
        ('import { Ros } from "roslib";\n\nconst a = (1;\n', 3, 13, "SyntaxError"),
        ("const a = 1;\nawait f(\n", 3, 0, "SyntaxError: Unexpected end of input"),
        ('x = "abc\n', 1, 5, "SyntaxError: Invalid or unexpected token"),
        ("const a = 1;\nreturn 2;\n", 2, 1, "SyntaxError: Illegal return statement"),
    ],
    ids=["token", "later-line", "end-of-input", "string", "return"],
)
def test_a_script_that_does_not_parse_is_told_where(text, line, column, said):
    """Node's message, its line (within the script) and its column come back."""
    with pytest.raises(ScriptError) as caught:
        check(text)
    assert (caught.value.line, caught.value.column) == (line, column)
    assert caught.value.message.startswith(said)
    assert str(caught.value).startswith(f"controller.mjs, line {line}")


@needs_node
def test_a_module_with_top_level_await_parses_and_nothing_runs(tmp_path):
    """A module that would write a file when run is only parsed."""
    marker = tmp_path / "ran"
    check(
        f'import {{ writeFileSync }} from "node:fs";\nawait 0;\nwriteFileSync("{marker}", "x");\n'
    )
    assert not marker.exists()


def test_too_large_a_script_and_no_node_are_refused(monkeypatch):
    """Over MAX_SCRIPT is refused before Node runs; without Node, NoNode says so."""
    with pytest.raises(PlaygroundError, match="at most 256 KiB"):
        check("//" + "x" * playground.MAX_SCRIPT)
    monkeypatch.setattr(shutil, "which", lambda name: None)
    with pytest.raises(NoNode, match=r"Node\.js 20"):
        check("const a = 1;\n")


@needs_node
@pytest.mark.parametrize("task", registry.names())
def test_every_tasks_starting_script_parses(task):
    """The script /playground starts from for each task is a module Node parses."""
    check(playground.template(task))


@needs_node
def test_the_starting_script_of_a_task_without_one_parses():
    """A task with no script of its own starts from one that watches its topics."""
    text = playground._watcher("some-task", ["/odom", "/camera/image/compressed", "/bumper"])
    check(text)
    assert '["/odom", "/bumper"]' in text  # images are left out


def test_a_script_is_committed_as_a_controller_repository(tmp_path):
    """The files load as a lab.toml the trial runner takes (node, the task), need no npm
    install (no dependencies), and give the script back."""
    script = Script("console.log(1);\n", "pr2-table")
    made = files(script, "alice", "Grasp.1")
    for name, data in made.items():
        (tmp_path / name).write_bytes(data)
    loaded = controller.load(tmp_path)
    assert (loaded.command, loaded.task) == (("node", "controller.mjs"), "pr2-table")
    assert not loaded.node_packages  # roslib is the lab's; nothing to install
    package = json.loads(made["package.json"])
    assert package["type"] == "module" and "dependencies" not in package
    assert package["name"] == "grasp.1"
    assert playground.script_of(made) == script
    assert playground.script_of({"controller.mjs": b"x"}) is None


@needs_node
async def test_check_answers_the_line_and_needs_a_writer(api, token):
    """POST /api/playground/check: ok, or the error at its line; 401 anonymously."""
    good = await api.post("/api/playground/check", json={"script": "1;\n"}, headers=auth(token))
    assert good.status_code == 200 and good.json() == {
        "ok": True,
        "error": None,
        "line": None,
        "column": None,
    }
    bad = await api.post(
        "/api/playground/check", json={"script": "1;\nlet = ;\n"}, headers=auth(token)
    )
    assert bad.status_code == 200
    assert (bad.json()["ok"], bad.json()["line"]) == (False, 2)
    anonymous = await api.post("/api/playground/check", json={"script": "1;\n"})
    assert anonymous.status_code == 401


@needs_node
async def test_run_as_a_trial_refuses_and_commits_nothing(api, service, token):
    """A script that does not parse (422, with its line), an unknown task (404), a bad
    repository name (422) and a lab not serving HTTP (503) commit nothing."""
    service.serving_at("http://lab.test")
    body = {"name": "maze", "task": "icreate-maze", "script": "let x = ;\n"}
    bad = await api.post("/api/playground/trials", json=body, headers=auth(token))
    assert bad.status_code == 422
    assert bad.json()["error"].startswith("controller.mjs, line 1, column 9: SyntaxError")
    unknown = await api.post(
        "/api/playground/trials", json={**body, "task": "nope"}, headers=auth(token)
    )
    assert unknown.status_code == 404 and "icreate-maze" in unknown.json()["error"]
    named = await api.post(
        "/api/playground/trials", json={**body, "name": "../x"}, headers=auth(token)
    )
    assert named.status_code == 422
    service.git_url = None
    unserved = await api.post(
        "/api/playground/trials", json={**body, "script": "1;\n"}, headers=auth(token)
    )
    assert unserved.status_code == 503 and "HTTP" in unserved.json()["error"]
    assert service.hosted.names("alice") == []
    assert service.index.find(Filters(), limit=10).items == []  # and no trial


async def test_reading_a_script_that_is_not_there_is_404(api):
    """GET /api/playground/USER/NAME of nothing hosted is a 404 that says so."""
    missing = await api.get("/api/playground/alice/maze")
    assert missing.status_code == 404 and "alice" in missing.json()["error"]


@pytest.mark.parametrize(
    ("given", "kept"),
    [
        ("https://lab.example.org", "https://lab.example.org"),
        ("http://10.0.0.5:8080/", "http://10.0.0.5:8080"),
        (None, None),
    ],
)
def test_public_url_is_an_address_without_a_path(given, kept):
    """--public-url keeps scheme and host (a trailing slash dropped)."""
    assert serve.public_url(given) == kept


@pytest.mark.parametrize(
    "given", ["lab.example.org", "ftp://lab", "https://lab/x", "https://lab?q=1", "https://"]
)
def test_public_url_refuses_what_is_not_an_address(given):
    """Anything but http(s)://HOST[:PORT] is refused in one line naming the flag."""
    with pytest.raises(serve.Refused, match="--public-url"):
        serve.public_url(given)
