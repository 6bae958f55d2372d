"""The lab's home page in a real browser (Debian's Chromium) at 1280x800, a laptop's
screen: what a person looks for first is there before any scrolling.

A real lab (no worker, one live robot) is filled the way workers fill it: trials of
several tasks filed with their outcomes, a dev evaluation of each of two commits scored,
a trial running, a held-out evaluation with an episode running and the rest queued, and
trials waiting. The page must show what runs, the recent trials, the latest evaluations
with their rates and the leaderboards above the fold, every task in a grid below, and
nothing of the held-out episodes.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from labd.sim import registry
from repository.evaluation import EvaluationRequest
from repository.index import User
from repository.trial import Filing, Order
from scheduler.fetch import FetchPolicy
from tests.helpers.githttp import GitRepo
from tests.helpers.labs import ServerThread, lab_config, running
from tests.integration.browser import Watched, browser

__all__ = ["browser"]
pytestmark = [pytest.mark.integration, pytest.mark.timeout(180)]
SHOTS = Path(__file__).resolve().parents[2] / "build" / "screenshots"
FOLD = 800  # a 1280x800 screen's first view
# the longest names among them: the tables must hold them
TASKS = ("icreate-maze", "dmc-cartpole-balance_sparse", "dmc-ball_in_cup-catch", "pr2-table")
DEV = ["success"] * 14 + ["fail"] * 4 + ["error"] * 2  # the dev suite's 20 episodes
EARLIER = ["success", "fail"] * 10


@pytest.fixture
def server(tmp_path: Path) -> Any:
    """A lab with no worker and one live robot, taking local repositories."""
    fetch = FetchPolicy(schemes=frozenset({"file"}))
    with running(lab_config(tmp_path / "data", service={"fetch": fetch})) as server:
        yield server


@pytest.fixture
def home(browser: Any) -> Any:
    """A page the size of a 1280x800 screen (the shared fixture's is taller)."""
    context = browser.new_context(viewport={"width": 1280, "height": FOLD})
    page = context.new_page()
    seen = Watched(page)
    page.on("console", lambda m: seen.errors.append(m.text) if m.type == "error" else None)
    page.on("pageerror", lambda e: seen.errors.append(str(e)))
    yield seen
    context.close()


class Filler:
    """Fills the lab's queue and archive as submitters and workers would."""

    def __init__(self, server: ServerThread, repo: GitRepo) -> None:
        self.service = server.lab.service
        self.service.queue.check = None  # the filings below name no record
        self.repo = repo
        for name in ("ann", "ben", "erin"):
            self.service.index.add_user(name, max_running=50, max_daily=500)

    def user(self, name: str) -> User:
        return self.service.index.user(name)

    def submit(self, name: str, task: str, seed: int, commit: str) -> int:
        order = Order(
            repository=str(self.repo.path),
            ref="main",
            commit=commit,
            task=task,
            seed=seed,
            public=True,
        )
        return self.service.queue.submit(self.user(name), order)

    def claim(self, worker: str) -> int:
        """The next queued trial, claimed by ``worker`` (the test queues one at a time)."""
        claimed = self.service.queue.claim(worker)
        assert claimed is not None
        return claimed.id

    def finish(self, trial_id: int, worker: str, outcome: str, reward: float) -> None:
        filing = Filing(
            status="finished",
            outcome=outcome,
            reason=f"{outcome} at tick 90",
            data_digest=f"{trial_id:064x}",
            metrics={"reward": reward},
        )
        assert self.service.queue.finish(trial_id, worker, filing)

    def evaluate(self, name: str, ref: str, suite: str = "dev") -> tuple[int, list[int]]:
        request = EvaluationRequest(
            repository=str(self.repo.path), ref=ref, task="icreate-maze", suite=suite
        )
        made = self.service.evaluator.submit(self.user(name), request)
        return made, self.service.evaluations.trials(made)


def fill(server: ServerThread, repo: GitRepo) -> dict[str, Any]:
    """The lab as a person finds it mid-afternoon (see the module's docstring)."""
    f = Filler(server, repo)
    first, second = repo.rev("v1"), repo.rev("main")
    evaluations = []
    for ref, outcomes in (("v1", EARLIER), ("main", DEV)):
        made, episodes = f.evaluate("erin", ref)
        for episode, outcome in zip(episodes, outcomes, strict=True):
            assert f.claim("w1") == episode
            f.finish(episode, "w1", outcome, 1.0 if outcome == "success" else 0.0)
        evaluations.append(made)
    for n in range(8):
        trial = f.submit(("ann", "ben")[n % 2], TASKS[n % len(TASKS)], n, second)
        assert f.claim("w1") == trial
        f.finish(trial, "w1", ("success", "fail", "success", "error")[n % 4], 100.0 * n / 3)
    running_public = f.submit("ann", "dmc-cheetah-run", 9, second)
    assert f.claim("w1") == running_public
    held_out, held_episodes = f.evaluate("erin", "main", suite="test")
    running_held = f.claim("w2")
    assert running_held in held_episodes
    waiting = [f.submit("ben", "icreate-maze", 10 + n, first) for n in range(3)]
    return {
        "evaluations": evaluations,
        "running": running_public,
        "held_out": held_out,
        "held_running": running_held,
        "held_queued": len(held_episodes) - 1,
        "waiting": waiting,
    }


def box(page: Any, selector: str) -> dict[str, float]:
    found = page.eval_on_selector(
        selector,
        "e => { const r = e.getBoundingClientRect();"
        " return {top: r.top, bottom: r.bottom, left: r.left, width: r.width}; }",
    )
    assert isinstance(found, dict), selector
    return found


def test_the_home_page_shows_what_a_person_looks_for_first(tmp_path, server, home: Watched):
    """At 1280x800, before scrolling: what runs and waits (public trials alone), the
    recent trials, the latest evaluations with their success rates, and the leaderboards
    of the suites evaluated; below, the tasks in a grid of several columns whose
    descriptions read as lines, not two words a line; no sideways scrolling."""
    toml = '[controller]\ncommand = ["python", "c.py"]\ntask = "icreate-maze"\n'
    repo = GitRepo.create(tmp_path / "ctl", {"lab.toml": toml, "c.py": "print('one')\n"})
    repo.tag("v1")
    repo.commit({"c.py": "print('two')\n"}, "two")
    made = fill(server, repo)
    page = home.page
    page.goto(server.http_url("/"))
    page.wait_for_load_state("networkidle")
    SHOTS.mkdir(parents=True, exist_ok=True)
    page.screenshot(path=str(SHOTS / "home.png"))
    page.screenshot(path=str(SHOTS / "home-full.png"), full_page=True)

    for selector in (
        "#now h2",
        f"#now a[href='/trials/{made['running']}']",
        "#recent tbody tr:first-child",
        "#evaluations tbody tr:first-child",
        "#leaderboards a[href='/tasks/icreate-maze?suite=dev#leaderboard']",
    ):
        assert box(page, selector)["bottom"] <= FOLD, selector

    now = page.locator("#now").inner_text()
    assert "1 running" in now and "3 waiting" in now, now  # the held-out episodes left out
    assert f"#{made['held_running']}" not in now
    assert page.locator(f"#now a[href='/trials/{made['held_running']}']").count() == 0
    latest = page.locator("#evaluations tbody tr").first.inner_text()
    assert f"#{made['held_out']}" in latest and "held out" in latest  # no score while it runs
    scored = page.locator(f"#evaluations tr:has(a[href='/evaluations/{made['evaluations'][1]}'])")
    assert "70 % (48 %\u201385 %, 95 % Wilson) of 20 episodes" in scored.inner_text()

    cards = page.eval_on_selector_all(
        "#tasks .catalogue > li",
        "items => items.map(i => { const r = i.getBoundingClientRect();"
        " return {left: r.left, top: r.top, width: r.width}; })",
    )
    assert len(cards) == len(registry.names())  # every task: the lab's, the packs'
    columns = {round(c["left"]) for c in cards}
    assert len(columns) >= 3, columns
    assert min(c["width"] for c in cards) >= 250
    assert box(page, "#tasks")["top"] > box(page, "#evaluations")["top"]  # below, not beside
    width = page.evaluate("() => document.documentElement.scrollWidth")
    assert width <= 1280, width
    height = page.evaluate("() => document.documentElement.scrollHeight")
    assert height < 2900, (
        height
    )  # a page (30 tasks in rows of 3 or more), not the 5,000 px of one column
    assert home.errors == []
