"""The archive's pages in a real browser, against a real lab with real trials.

Every page renders with no console error and no request leaving 127.0.0.1; the list
filters and pages; a crash's traceback reads on its trial's page; a rerun made with the
page's button shows its verdict; what a controller prints runs nothing.
"""

from __future__ import annotations

import time
from pathlib import Path

import pytest

from tests.helpers.githttp import GitRepo
from tests.helpers.labs import ServerThread, lab_config, running
from tests.integration.browser import Watched, browser, watched

__all__ = ["browser", "watched"]
pytestmark = [pytest.mark.integration, pytest.mark.timeout(300)]
SHOTS = Path(__file__).resolve().parents[2] / "build" / "screenshots"

STEPS = """\
import sys
from controllers.client import Lab
print("<script>document.title='owned'</script>")
with Lab.connect() as lab:
    for _ in range(5):
        lab.step()
if len(sys.argv) > 1:
    raise RuntimeError("the controller has a bug")
"""


@pytest.fixture
def server(tmp_path, cache):
    """A lab with one worker (bubblewrap) and no robots, its HTTP port chosen freely."""
    with running(lab_config(tmp_path / "data", (), workers=1, cache=cache)) as server:
        yield server


def wait_ended(server: ServerThread, trial_id: int, timeout: float = 120):
    service = server.lab.service
    deadline = time.monotonic() + timeout
    while not (trial := service.index.trial(trial_id)).status.ended:
        assert time.monotonic() < deadline, trial
        time.sleep(0.2)
    return trial


def shot(watched: Watched, name: str) -> None:
    SHOTS.mkdir(parents=True, exist_ok=True)
    watched.page.screenshot(path=str(SHOTS / f"{name}.png"), full_page=True)


def test_the_archive_in_a_browser(server, watched, tmp_path):
    """A person signs in, submits a controller that crashes and one that runs, reads the
    traceback, filters the list, reruns from the page and sees the verdict; every page
    renders cleanly and nothing leaves the machine."""
    service = server.lab.service
    token = service.index.add_user("alice")
    toml = '[controller]\ncommand = ["python", "c.py"{extra}]\ntask = "icreate-maze"\n'
    good = GitRepo.create(tmp_path / "good", {"lab.toml": toml.format(extra=""), "c.py": STEPS})
    bad = GitRepo.create(
        tmp_path / "bad", {"lab.toml": toml.format(extra=', "crash"'), "c.py": STEPS}
    )
    page = watched.page
    page.goto(server.http_url("/"))
    assert page.locator("h1").first.inner_text() == "A remote robot lab"
    page.goto(server.http_url("/session?then=/submit"))
    page.fill("input[name=token]", token)
    page.click("#token-signin button[type=submit]")
    page.wait_for_url("**/submit")
    made = {}
    for name, repo in (("bad", bad), ("good", good)):
        page.goto(server.http_url("/submit"))
        page.fill("#repository", str(repo.path))
        page.click("form.card button[type=submit]")
        page.wait_for_url("**/trials/*")
        made[name] = int(page.url.rsplit("/", 1)[1])
    for trial_id in made.values():
        wait_ended(server, trial_id)

    page.goto(server.http_url(f"/trials/{made['bad']}"))
    assert page.locator(".headline .badge").inner_text().lower() == "error"
    assert "RuntimeError: the controller has a bug" in page.locator("#reason").inner_text()
    traceback = page.locator("#stderr pre").inner_text()
    assert 'File "/code/c.py", line 8' in traceback and "RuntimeError" in traceback
    assert page.title() != "owned"  # what the controller printed was shown, not run
    assert "<script>document.title='owned'</script>" in page.locator("#stdout pre").inner_text()
    shot(watched, "trial-error")

    page.goto(server.http_url("/trials"))
    page.select_option("select[name=outcome]", "fail")
    page.click("form.filters button[type=submit]")
    page.wait_for_url("**outcome=fail**")
    rows = page.locator("table.trials tbody tr")
    assert rows.count() == 1 and f"#{made['good']}" in rows.first.inner_text()
    shot(watched, "trials")

    deadline = time.monotonic() + 60  # the worker replays a record once it is filed
    while "replay.json" not in service.index.derived(made["good"]):
        assert time.monotonic() < deadline, "no replay filed"
        time.sleep(0.2)
    page.goto(server.http_url(f"/trials/{made['good']}"))
    assert page.locator("#replay").inner_text().startswith("Replay: verified")
    assert "renders it when you play it" in page.locator("#video-note").inner_text()
    duration = page.eval_on_selector(  # as pressing play does: the lab renders it now
        "#video",
        """video => new Promise((ok, no) => {
            video.onloadedmetadata = () => ok(video.duration);
            video.onerror = () => no(String(video.error && video.error.message));
            video.preload = "metadata";
            video.load();
        })""",
    )
    assert 0.4 < duration < 1.0  # six frames, ticks 0 to 5, at 10 frames a second
    page.click("#rerun")
    page.wait_for_url("**/trials/*")
    rerun = int(page.url.rsplit("/", 1)[1])
    assert rerun != made["good"]
    wait_ended(server, rerun)
    page.reload()
    assert page.locator(".reproduced").first.inner_text() == "reproduced"
    assert f"trial #{made['good']}" in page.locator(".card").first.inner_text()
    page.goto(server.http_url(f"/commits/{good.rev()}"))
    assert "1 reproduced" in page.locator("main").inner_text()
    shot(watched, "commit")

    for path in ("/", "/tasks/icreate-maze", "/docs", "/redoc", "/trials/424242"):
        page.goto(server.http_url(path))
        page.wait_for_load_state("networkidle")
    assert page.locator("h1").inner_text() == "No trial 424242"
    watched.expected.add(f"404 {server.http_url('/trials/424242')}")
    page.goto(server.http_url("/docs"))
    page.wait_for_selector(".swagger-ui .opblock", timeout=20_000)
    shot(watched, "docs")
    watched.check()
