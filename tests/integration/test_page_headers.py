"""Every page under its Content-Security-Policy, in a real browser against a real lab.

Each page (the archive's, a trial with its record in plots and 3D, a task, both live
robots through the bridge, the API's docs in Swagger UI and ReDoc, reservations,
sign-in) works as it does without one, while the browser reports no violation of the
policy; each carries the policy, nosniff and its referrer policy; and another site's
page cannot frame the lab.
"""

from __future__ import annotations

import time

import pytest

from repository.trial import TrialRequest
from tests.helpers.githttp import GitRepo
from tests.helpers.labs import MAZE, PR2, lab_config, running
from tests.helpers.timing import SECOND
from tests.integration.browser import Watched, browser, watched
from tests.integration.test_browser import wait_ended

__all__ = ["browser", "watched"]
pytestmark = [pytest.mark.integration, pytest.mark.timeout(400)]

STEPS = """\
from controllers.client import EpisodeOver, Lab

with Lab.connect() as lab:
    try:
        for tick in range(30):
            lab.publish("/cmd_vel", "geometry_msgs/msg/Twist", {"linear": {"x": 0.15}})
            lab.step()
    except EpisodeOver:
        pass
"""
# Violations the page reports to itself (a securitypolicyviolation event), kept for the test.
LISTEN = """
window.__csp = [];
document.addEventListener("securitypolicyviolation", (e) =>
  window.__csp.push(`${e.effectiveDirective} blocked ${e.blockedURI || "inline"}`
                    + ` at ${e.sourceFile}:${e.lineNumber}`));
"""
MS = 1000


@pytest.fixture(scope="module")
def server(tmp_path_factory, cache):
    """Both live robots, the archive, and one worker (bubblewrap) for a trial's record."""
    data = tmp_path_factory.mktemp("headers") / "data"
    with running(lab_config(data, (MAZE, PR2), workers=1, cache=cache)) as server:
        yield server


@pytest.fixture(scope="module")
def trial(server, tmp_path_factory) -> int:
    """A finished trial of the maze, its record summarized for its page."""
    toml = '[controller]\ncommand = ["python", "c.py"]\ntask = "icreate-maze"\n'
    repo = GitRepo.create(tmp_path_factory.mktemp("repo") / "r", {"lab.toml": toml, "c.py": STEPS})
    service = server.lab.service
    service.index.add_user("alice")
    alice = service.index.user("alice")
    made = service.submissions.submit(alice, TrialRequest(repository=str(repo.path)))
    service.wake()
    done = wait_ended(server, made, timeout=180)
    assert done.mcap, done.reason
    return made


# page, and what shows that it works (a JavaScript condition), beyond loading
PAGES: list[tuple[str, str]] = [
    ("/", "document.querySelector('main h1, main h2') !== null"),
    ("/trials", "document.querySelector('table') !== null"),
    ("/trials/{trial}", "['plots', 'map', 'scene'].every(p =>"
     " (document.getElementById('record').dataset.drawn || '').includes(p))"),
    ("/tasks/icreate-maze", "document.querySelector('main h1') !== null"),
    ("/robots/icreate-1?interface=video",
     "document.body.dataset.ready === 'yes'"
     " && Number(document.getElementById('camera').dataset.frames || 0) >= 2"),
    ("/robots/pr2-1",
     "document.body.dataset.ready === 'yes'"
     " && Number(document.getElementById('pr2-scene')?.dataset.frames || 0) > 3"),
    ("/docs", "document.querySelector('.swagger-ui .opblock') !== null"),
    ("/redoc", "document.querySelector('#redoc h1') !== null"
     " && document.querySelector('#redoc [data-section-id]') !== null"),
    ("/reservations", "document.querySelector('main') !== null"),
    ("/session", "document.getElementById('password-signin') !== null"),
]  # fmt: skip


@pytest.mark.parametrize(("path", "works"), PAGES, ids=[p for p, _ in PAGES])
def test_each_page_works_under_its_policy(server, trial, watched: Watched, path: str, works: str):
    """The page does what it does (draws its record, shows the robot's camera or 3D
    scene over the bridge, renders the API's docs) with no violation of its
    Content-Security-Policy, which forbids framing, and nosniff and same-origin referrers."""
    page = watched.page
    page.add_init_script(LISTEN)
    answer = page.goto(server.http_url(path.format(trial=trial)))
    assert answer is not None and answer.status == 200
    headers = answer.headers
    policy = headers["content-security-policy"]
    assert "frame-ancestors 'none'" in policy and "default-src 'self'" in policy
    assert "'unsafe-inline'" not in policy and "'unsafe-eval'" not in policy
    assert headers["x-content-type-options"] == "nosniff"
    assert headers["referrer-policy"] == "same-origin"
    page.wait_for_function(works, timeout=60 * MS)
    page.wait_for_timeout(500)  # a late violation (a style made after the first draw)
    assert page.evaluate("window.__csp") == []
    watched.check()


def test_another_site_cannot_frame_the_lab(server, browser):
    """A page of another origin that frames the lab's sign-in page gets an empty frame."""
    context = browser.new_context()
    try:
        page = context.new_page()
        refused: list[str] = []
        page.on(
            "console", lambda m: refused.append(m.text) if "frame-ancestors" in m.text else None
        )
        target = server.http_url("/session")
        page.set_content(f'<iframe id="f" src="{target}" width="600" height="400"></iframe>')
        deadline = time.monotonic() + 60 * SECOND
        while not refused and time.monotonic() < deadline:  # until the browser says so
            page.wait_for_timeout(50)  # lets the page's events in: a poll, not a wait for time
        frame = page.frame_locator("#f")
        assert frame.locator("#password-signin").count() == 0
        assert refused, "the browser did not say it refused the frame"
    finally:
        context.close()
