"""The playground in a real browser, against a real lab (a live maze robot, a bubblewrap
worker, the lab's own git server).

Run live: the script runs in the page's sandboxed frame against the live robot, drives
it, prints beside the camera; Stop ends its drive; a syntax error is marked at its line
before anything runs, and a runtime error at the line it was thrown from. Run as a
trial: a script that does not parse is refused at its line with nothing committed; one
that parses is committed to the person's hosted repository and runs as a trial under
Node in lockstep; the trial page links back to the script; a rerun reads "reproduced";
and a clone of the hosted repository, run with `labd run`, gives the same data digest.
Screenshots go to build/screenshots/.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time

import httpx
import pytest

from labd.playground import template
from tests.helpers.githttp import GIT_ENV
from tests.helpers.labs import MAZE, ServerThread, lab_config, running, shared_cache
from tests.integration.browser import browser, watched
from tests.integration.test_browser import shot, wait_ended

__all__ = ["browser", "watched"]
pytestmark = [pytest.mark.integration, pytest.mark.timeout(400)]

# The maze's starting script, ending after 40 ticks (a trial's outcome is then "fail":
# the controller left before the episode's end; what matters here is that it reproduces).
SHORT = (
    template("icreate-maze")
    .replace("  if (!(await tick())) break;", "  if (!(await tick()) || ++ticks >= 40) break;")
    .replace("let bumps = 0;", "let bumps = 0;\nlet ticks = 0;")
)


@pytest.fixture(scope="module")
def server(tmp_path_factory, cache):
    """A lab with the live maze robot and one bubblewrap worker; alice may write."""
    data = tmp_path_factory.mktemp("playground") / "data"
    with running(lab_config(data, (MAZE,), workers=1, cache=cache)) as server:
        server.token = server.lab.service.index.add_user("alice")
        yield server


def set_script(page, text: str) -> None:
    """Replace the editor's script, as typing it would."""
    page.evaluate(
        """text => { const v = window.labPlayground.editor;
            v.dispatch({changes: {from: 0, to: v.state.doc.length, insert: text}}); }""",
        text,
    )


def sign_in(server: ServerThread, page) -> None:
    page.goto(server.http_url("/session?then=/playground"))
    page.fill("input[name=token]", server.token)
    page.click("#token-signin button[type=submit]")
    page.wait_for_url("**/playground")


def driver(server: ServerThread) -> str:
    current = server.lab.drives["icreate-1"].current
    return current.user if current is not None else ""


def test_run_live_drives_the_robot_and_prints_beside_the_camera(server, watched):
    """An anonymous visitor runs the maze's script live: it becomes the driver, its
    lines appear beside the camera, and Stop ends the drive; a syntax error is marked at
    its line and nothing runs; an error thrown at run time is shown with its line."""
    page = watched.page
    page.goto(server.http_url("/robots/icreate-1"))
    page.click("#playground-link")
    page.wait_for_url("**/playground?robot=icreate-1")
    page.wait_for_function("document.body.dataset.ready === 'yes'")
    assert page.locator("#robot").input_value() == "icreate-1"
    assert "lab/step" in page.evaluate("() => window.labPlayground.editor.state.doc.toString()")

    page.click("#run-live")
    page.wait_for_function("Number(document.getElementById('console').dataset.lines || 0) >= 1")
    assert page.locator("#console").inner_text().startswith("live: on the robot's clock")
    server.wait_until(lambda: driver(server) != "", timeout=20)  # its /cmd_vel made it the driver
    page.wait_for_function("Number(document.getElementById('camera').dataset.frames || 0) > 2")
    shot(watched, "playground-live")
    page.click("#stop")
    server.wait_until(
        lambda: driver(server) == "", timeout=20
    )  # its connection went with the frame
    assert page.locator("#run-live").is_enabled()

    set_script(page, "const a = 1;\nconst b = (a;\n")
    page.click("#run-live")
    assert page.locator("#status").inner_text().startswith("line 2: SyntaxError")
    assert page.locator(".cm-lint-marker-error").count() == 1
    assert page.locator("#stop").is_disabled()  # nothing ran

    set_script(page, 'console.log("one");\nconsole.warn({ two: 2 });\nthrow new Error("boom");\n')
    page.click("#run-live")
    page.wait_for_function("document.body.dataset.running === 'no'")
    assert page.locator("#console").inner_text().splitlines() == [
        "one",
        '{"two":2}',
        "Error: boom (line 3)",
    ]
    assert "line 3" in page.locator("#status").inner_text()
    watched.check()


def test_a_script_becomes_a_trial_that_reproduces_and_clones(server, watched, cache, tmp_path):
    """Alice's script that does not parse is refused at its line, nothing committed; the
    one that parses becomes a commit of her hosted repository and a trial of it, whose
    page links back to the script; its rerun reads "reproduced"; a clone over git's HTTP,
    run with labd run, gives the trial's data digest."""
    service = server.lab.service
    page = watched.page
    sign_in(server, page)
    page.goto(server.http_url("/tasks/icreate-maze"))
    page.click("#playground-link")
    page.wait_for_function("document.body.dataset.ready === 'yes'")
    page.fill("#name", "wanderer")

    set_script(page, SHORT.replace("let backing = 0;", "let backing = ;"))
    page.click("#run-trial")
    page.wait_for_function("document.getElementById('status').dataset.level === 'error'")
    said = page.locator("#status").inner_text()
    line = SHORT.splitlines().index("let backing = 0; // ticks left backing off and turning") + 1
    assert said.startswith(f"line {line}: SyntaxError") and "nothing was committed" in said
    assert service.hosted.head("alice", "wanderer") is None

    set_script(page, SHORT)
    page.click("#run-trial")
    page.wait_for_function("document.getElementById('result').dataset.trial !== undefined")
    trial_id = int(page.locator("#result").get_attribute("data-trial"))
    commit = page.locator("#result").get_attribute("data-commit")
    assert service.hosted.head("alice", "wanderer") == commit
    trial = wait_ended(server, trial_id)
    assert (trial.commit, trial.repository) == (commit, f"{service.git_url}/alice/wanderer.git")
    assert trial.outcome.value == "fail", trial.reason  # it left after 40 ticks, as written
    assert "before the episode ended" in trial.reason
    page.wait_for_function("document.getElementById('result').dataset.ended === 'finished'")
    assert page.locator("#status").inner_text().startswith(f"trial #{trial_id} finished · fail")
    shot(watched, "playground-trial")

    page.click("#trial-link")
    page.wait_for_url(f"**/trials/{trial_id}")
    page.click("#playground-link")
    page.wait_for_url("**/playground?repo=alice/wanderer*")
    page.wait_for_function("document.body.dataset.ready === 'yes'")
    shown = page.evaluate("() => window.labPlayground.editor.state.doc.toString()")
    assert shown == SHORT
    assert commit[:12] in page.locator("#opened").inner_text()

    rerun = httpx.post(
        server.http_url(f"/api/trials/{trial_id}/rerun"),
        headers={"Authorization": f"Bearer {server.token}"},
    )
    assert rerun.status_code == 201, rerun.text
    again = wait_ended(server, rerun.json()["id"])
    page.goto(server.http_url(f"/trials/{again.id}"))
    assert page.locator(".reproduced").first.inner_text() == "reproduced"
    watched.check()

    clone = tmp_path / "clone"
    url = f"{service.git_url}/alice/wanderer.git"
    env = {k: v for k, v in os.environ.items() if not k.startswith("GIT_")} | GIT_ENV
    subprocess.run(["git", "clone", "-q", url, str(clone)], check=True, env=env, timeout=60)
    data = tmp_path / "data"
    shared_cache(data, cache)
    started = time.monotonic()
    done = subprocess.run(
        [sys.executable, "-m", "labd", "run", str(clone), "--sandbox", "bwrap", "--data", str(data), "--json"],
        capture_output=True, text=True, timeout=300, check=False,
    )  # fmt: skip
    result = json.loads(done.stdout)
    assert result["data_digest"] == trial.data_digest, (
        result["reason"],
        time.monotonic() - started,
    )


def test_a_script_is_evaluated_on_a_suite_of_its_task(server, watched):
    """The page's Evaluate commits the script and queues an evaluation of that commit on
    every episode of the chosen suite; an unknown suite commits nothing."""
    service = server.lab.service
    auth = {"Authorization": f"Bearer {server.token}"}
    body = {"name": "evaluated", "task": "icreate-maze", "script": SHORT, "suite": "nope"}
    missing = httpx.post(server.http_url("/api/playground/evaluations"), json=body, headers=auth)
    assert missing.status_code == 404 and "no suite 'nope'" in missing.json()["error"]
    assert service.hosted.head("alice", "evaluated") is None

    page = watched.page
    sign_in(server, page)
    page.wait_for_function("document.body.dataset.ready === 'yes'")
    page.fill("#name", "evaluated")
    set_script(page, SHORT)
    assert page.locator("#suite").input_value() == "dev"
    page.click("#evaluate")
    page.wait_for_function("document.getElementById('result').dataset.evaluation !== undefined")
    evaluation_id = int(page.locator("#result").get_attribute("data-evaluation"))
    assert "20 episodes" in page.locator("#status").inner_text()
    evaluation = service.evaluations.get(evaluation_id)
    assert evaluation.repository == f"{service.git_url}/alice/evaluated.git"
    assert evaluation.commit == service.hosted.head("alice", "evaluated")
    shot(watched, "playground-evaluation")
    cancelled = httpx.post(
        server.http_url(f"/api/evaluations/{evaluation_id}/cancel"), headers=auth, timeout=60
    )
    assert cancelled.status_code == 200, cancelled.text
    page.click("#evaluation-link")
    page.wait_for_url(f"**/evaluations/{evaluation_id}")
    watched.check()


@pytest.fixture
def reserved(tmp_path):
    """A lab whose live maze robot is driven only in a reserved slot; alice has one now."""
    with running(lab_config(tmp_path / "data", (MAZE,), reservations=True)) as server:
        server.token = server.lab.service.index.add_user("alice")
        booked = httpx.post(
            server.http_url("/api/reservations"),
            json={"robot": "icreate-1", "minutes": 10},
            headers={"Authorization": f"Bearer {server.token}"},
        )
        assert booked.status_code == 201, booked.text
        yield server


def test_run_live_under_reservations_drives_with_the_slots_key(reserved, watched):
    """With reservations, a visitor without a slot is told to book one and nothing runs;
    alice's script connects with her slot's key and drives as alice."""
    page = watched.page
    page.goto(reserved.http_url("/playground?robot=icreate-1"))
    page.wait_for_function("document.body.dataset.ready === 'yes'")
    page.click("#run-live")
    page.wait_for_function("document.getElementById('status').dataset.level === 'warning'")
    assert "slot" in page.locator("#status").inner_text()
    assert page.locator("#stop").is_disabled() and driver(reserved) == ""

    sign_in(reserved, page)
    page.wait_for_function("document.body.dataset.ready === 'yes'")
    page.select_option("#task", "icreate-maze")
    page.wait_for_function("document.body.dataset.ready === 'yes'")
    page.click("#run-live")
    page.wait_for_function("Number(document.getElementById('console').dataset.lines || 0) >= 1")
    reserved.wait_until(lambda: driver(reserved) == "alice", timeout=20)
    page.click("#stop")
    reserved.wait_until(lambda: driver(reserved) == "", timeout=20)
    watched.check()
