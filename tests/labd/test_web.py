"""The pages in process: each renders, unknown things are pages that say so, and what a
user controls is escaped. (tests/integration/test_browser.py drives them in Chromium.)"""

from __future__ import annotations

import re

import httpx
import pytest
from markupsafe import escape

from labd.service import Service, ServiceConfig
from labd.web import RobotLink, Site, create_app
from labd.web.problems import PageRoute
from repository.trial import Filing, Order
from scheduler.fetch import FetchPolicy
from tests.fakes import file_unchecked
from tests.helpers.githttp import GitRepo
from tests.labd.test_api_edges import _leaves

SCRIPT = "<script>alert('owned')</script>"


@pytest.fixture
def service(tmp_path):
    config = ServiceConfig(
        data=tmp_path / "data", workers=0, fetch=FetchPolicy(schemes=frozenset({"file"}))
    )
    service = Service(config)
    yield service
    service.index.close()


@pytest.fixture
async def web(service):
    site = Site((RobotLink("icreate-1", "icreate-maze", True),), bridge_port=9999)
    app = create_app(service, site, on_submit=lambda: None)
    transport = httpx.ASGITransport(app=app)
    async with httpx.AsyncClient(transport=transport, base_url="http://lab.test") as client:
        yield client


@pytest.fixture
def token(service):
    return service.index.add_user("alice")


@pytest.fixture
def repo(tmp_path):
    toml = '[controller]\ncommand = ["python", "c.py"]\ntask = "icreate-maze"\n'
    return GitRepo.create(tmp_path / "ctl", {"lab.toml": toml, "c.py": "pass\n"})


def queue(service, repo, **kwargs):
    alice = service.index.user("alice")
    order = Order(
        repository=str(repo.path),
        ref=kwargs.pop("ref", "main"),
        commit=repo.rev(),
        task="icreate-maze",
        params=kwargs.pop("params", {}),
        seed=kwargs.pop("seed", 0),
        public=True,
        **kwargs,
    )
    return service.queue.submit(alice, order)


def finish(service, trial_id, filing):
    claim = service.queue.claim("w")
    assert claim is not None and claim.id == trial_id
    assert file_unchecked(service, trial_id, "w", filing)


async def test_every_page_renders(web, service, token, repo):
    """The lab, the trial list, a trial, its commit, a task, the forms and the API docs
    all answer HTML (the docs from the lab's own files)."""
    trial_id = queue(service, repo)
    for path in (
        "/",
        "/trials",
        f"/trials/{trial_id}",
        f"/commits/{repo.rev()}",
        "/tasks/icreate-maze",
        "/submit",
        "/session",
        "/docs",
        "/redoc",
    ):
        reply = await web.get(path)
        assert reply.status_code == 200, (path, reply.text[:300])
        assert reply.headers["content-type"].startswith("text/html")
        links = re.findall(r'(?:src|href)="([^"]*)"', reply.text)
        outside = [u for u in links if "://" in u and not u.startswith("http://lab.test")]
        assert outside == [], (path, outside)  # every script, style and link is the lab's
    docs = (await web.get("/docs")).text
    assert "/static/vendor/swagger-ui/swagger-ui-bundle.js" in docs and "cdn" not in docs
    redoc = (await web.get("/redoc")).text
    assert "/static/vendor/redoc/redoc.standalone.js" in redoc and "googleapis" not in redoc
    home = (await web.get("/")).text
    assert "ws://lab.test:9999/robots/icreate-1" in home


async def test_unknown_things_are_pages_with_a_way_back(web):
    """An unknown trial, commit or task is a page a person can act on, not JSON, under
    the status and with the words the API answers the same error with (``/commits/zz``
    is no commit at all: 422)."""
    for path, api, status, title in (
        ("/trials/999", "/api/trials/999", 404, "No trial 999"),
        ("/commits/abcdef12", "/api/commits/abcdef12", 404, "No commit with trials abcdef12"),
        ("/commits/zz", "/api/commits/zz", 422, "Not accepted"),
        ("/tasks/juggling", None, 404, "Not found"),
    ):
        reply = await web.get(path)
        assert reply.status_code == status, path
        assert reply.headers["content-type"].startswith("text/html")
        assert f"<h1>{title}</h1>" in reply.text and 'href="/trials"' in reply.text
        if api is not None:
            said = await web.get(api)
            assert said.status_code == status
            assert str(escape(said.json()["error"])) in reply.text
    assert "no task &#39;juggling&#39;; the tasks are" in (await web.get("/tasks/juggling")).text


async def test_a_url_that_is_no_page_is_a_page_for_a_browser(web):
    """A browser (Accept: text/html) asking for a URL that is no route gets the 404
    page; a client that does not ask for HTML, or asks under /api/, gets JSON."""
    browser = {"Accept": "text/html,application/xhtml+xml"}
    page = await web.get("/signin", headers=browser)
    assert page.status_code == 404 and page.headers["content-type"].startswith("text/html")
    assert "<h1>Not found</h1>" in page.text and "no such page or API route: /signin" in page.text
    for path, headers in (("/signin", {}), ("/api/nothing", browser)):
        said = await web.get(path, headers=headers)
        assert said.status_code == 404 and said.headers["content-type"] == "application/json"
        assert said.json() == {"error": f"no such page or API route: {path}"}
    for path in ("/trials/abc", "/evaluations/-x", "/trials/99999999999999999999999"):
        page = await web.get(path, headers=browser)  # a page's URL that cannot name one
        assert page.status_code == 404, path
        assert page.headers["content-type"].startswith("text/html"), path
        assert f"no such page: {path}" in page.text, path
    said = await web.get("/api/trials/abc")
    assert said.status_code == 422 and "trial_id" in said.json()["error"]


def test_every_page_answers_errors_as_a_page(service):
    """Every route outside the API (its JSON under /api/, and the OpenAPI document) is a
    ``PageRoute``, so an error it raises is a page under the API's status, never JSON."""
    app = create_app(service, Site(), on_submit=lambda: None)
    pages = [r for r in _leaves(app.routes) if not r.path.startswith("/api/")]
    pages = [r for r in pages if r.path not in ("/healthz", "/readyz", "/metrics")]
    assert {"/", "/trials/{trial_id}", "/session", "/docs", "/reservations"} <= {
        r.path for r in pages
    }
    assert [r.path for r in pages if not isinstance(r, PageRoute)] == []


async def test_what_users_control_is_escaped(web, service, token, repo):
    """A controller printing <script>, and a ref or parameter holding one, run nothing."""
    trial_id = queue(service, repo, ref=SCRIPT, params={"note": SCRIPT})
    log = service.store.put_bytes(f"hello\n{SCRIPT}\n".encode())
    finish(
        service,
        trial_id,
        Filing.error(f"the controller exited with 1 at tick 0: {SCRIPT}").model_copy(
            update={"stdout": log, "stderr": log}
        ),
    )
    for path in (f"/trials/{trial_id}", "/trials", f"/commits/{repo.rev()}", "/"):
        text = (await web.get(path)).text
        assert SCRIPT not in text, path
    page = (await web.get(f"/trials/{trial_id}")).text
    assert "&lt;script&gt;alert(&#39;owned&#39;)&lt;/script&gt;" in page


async def test_a_huge_log_is_shown_in_part_with_a_link(web, service, token, repo):
    """A log longer than the page shows is cut to its end, with a link to the whole."""
    trial_id = queue(service, repo)
    log = service.store.put_bytes(b"x" * 200_000 + b"\nTraceback: the end\n")
    finish(service, trial_id, Filing.error("crashed").model_copy(update={"stderr": log}))
    page = (await web.get(f"/trials/{trial_id}")).text
    assert "Traceback: the end" in page
    assert f'href="/api/trials/{trial_id}/logs/stderr"' in page
    assert "x" * 70_000 not in page


async def test_filters_pages_and_order(web, service, token, repo):
    """The list filters by outcome and pages by cursor; by reward it pages by number."""
    ids = [queue(service, repo, seed=s) for s in range(3)]
    for n, trial_id in enumerate(ids):
        filing = Filing.success("done") if n != 1 else Filing.fail("timed out")
        finish(service, trial_id, filing.model_copy(update={"metrics": {"reward": float(n)}}))
    fails = (await web.get("/trials", params={"outcome": "fail"})).text
    assert f'href="/trials/{ids[1]}"' in fails and f'href="/trials/{ids[0]}"' not in fails
    bad = await web.get("/trials", params={"since": "yesterday"})
    assert bad.status_code == 422 and "YYYY-MM-DD" in bad.text
    by_reward = (await web.get("/trials", params={"order": "reward"})).text
    assert by_reward.index(f"#{ids[2]}<") < by_reward.index(f"#{ids[0]}<")


def csrf_of(html: str) -> str:
    """The CSRF token a page's forms carry."""
    found = re.search(r'<meta name="csrf-token" content="([^"]+)">', html)
    assert found, "the page has no CSRF token"
    return found.group(1)


async def test_submitting_and_rerunning_from_the_pages(web, service, token, repo):
    """Signed in with a token, a person submits from the form (lab.toml's task by default)
    and reruns from a trial's page; a bad request comes back on the form, kept; a form
    without the page's CSRF token, or from another site, is refused."""
    csrf = csrf_of((await web.get("/submit")).text)
    anonymous = await web.post("/submit", data={"repository": str(repo.path), "csrf": csrf})
    assert anonymous.status_code == 303  # to sign in first, and back to the form
    assert anonymous.headers["location"] == "/session?then=/submit"
    trial_id = queue(service, repo)
    anonymous = await web.post(f"/trials/{trial_id}/rerun", data={"csrf": csrf})
    assert anonymous.status_code == 303  # back to the trial's page, where its button is
    assert anonymous.headers["location"] == f"/session?then=/trials/{trial_id}"
    wrong = await web.post("/session", data={"token": "labd_nope", "csrf": csrf})
    assert wrong.status_code == 401
    signed = await web.post("/session", data={"token": token, "then": "/submit", "csrf": csrf})
    assert signed.status_code == 303 and signed.headers["location"] == "/submit"
    cookie = signed.headers["set-cookie"]
    assert cookie.startswith("labd_session=") and token not in cookie
    assert "httponly" in cookie.lower() and "samesite=strict" in cookie.lower()
    csrf = csrf_of((await web.get("/submit")).text)  # the session's own token now
    made = await web.post("/submit", data={"repository": str(repo.path), "seed": "4", "csrf": csrf})
    assert made.status_code == 303
    trial_id = int(made.headers["location"].rsplit("/", 1)[1])
    assert service.index.trial(trial_id).task == "icreate-maze"
    refused = await web.post(
        "/submit", data={"repository": str(repo.path), "params": "maze_size=8", "csrf": csrf}
    )
    assert refused.status_code == 422 and "must be odd" in refused.text
    assert 'value="maze_size=8"' in refused.text
    again = await web.post(f"/trials/{trial_id}/rerun", data={"csrf": csrf})
    assert again.status_code == 303
    rerun = service.index.trial(int(again.headers["location"].rsplit("/", 1)[1]))
    assert rerun.rerun_of == trial_id
    forged = await web.post(
        f"/trials/{trial_id}/rerun", data={"csrf": csrf}, headers={"Origin": "http://evil.example"}
    )
    assert forged.status_code == 403 and forged.headers["content-type"].startswith("text/html")
    assert "sent from the lab&#39;s own pages" in forged.text
    bare = await web.post(f"/trials/{trial_id}/rerun")
    assert bare.status_code == 403 and "This form had no CSRF token" in bare.text
    stale = await web.post(f"/trials/{trial_id}/rerun", data={"csrf": "from-an-old-page"})
    assert stale.status_code == 403 and "Reload the page and send it again" in stale.text
