"""An evaluation's pages in a real browser (Debian's Chromium), against a real lab.

The lab runs no worker: the test files the episodes the way a worker does, while the
evaluation's page is open, and the page follows them through the API without
reloading; then two evaluations are compared from the "Compare with…" form, and the
task's page ranks them.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from repository.evaluation import EvaluationRequest, compare
from repository.trial import Filing
from scheduler.fetch import FetchPolicy
from tests.fakes import verify_episodes
from tests.helpers.githttp import GitRepo
from tests.helpers.labs import ServerThread, lab_config, running
from tests.integration.browser import Watched, browser, watched

__all__ = ["browser", "watched"]
pytestmark = [pytest.mark.integration, pytest.mark.timeout(180)]
SHOTS = Path(__file__).resolve().parents[2] / "build" / "screenshots"
MS = 1000
OUTCOMES = ["success"] * 12 + ["fail"] * 5 + ["error"] * 3  # the dev suite's 20 episodes


@pytest.fixture
def server(tmp_path):
    """A lab with no worker and no robot, taking local repositories."""
    fetch = FetchPolicy(schemes=frozenset({"file"}))
    with running(lab_config(tmp_path / "data", (), service={"fetch": fetch})) as server:
        yield server


@pytest.fixture
def repo(tmp_path) -> GitRepo:
    toml = '[controller]\ncommand = ["python", "c.py"]\ntask = "icreate-maze"\n'
    made = GitRepo.create(tmp_path / "ctl", {"lab.toml": toml, "c.py": "print('one')\n"})
    made.tag("v1")
    made.commit({"c.py": "print('two')\n"}, "two")
    return made


def evaluated(server: ServerThread, ref: str, repo: GitRepo) -> int:
    service = server.lab.service
    user = service.index.user("erin")
    request = EvaluationRequest(repository=str(repo.path), ref=ref, task="icreate-maze")
    return service.evaluator.submit(user, request)


def claim(server: ServerThread, trial_id: int) -> None:
    service = server.lab.service
    service.queue.check = None  # the filings below name no record
    claimed = service.queue.claim("w")
    assert claimed is not None and claimed.id == trial_id


def finish(server: ServerThread, trial_id: int, outcome: str, reward: float) -> None:
    """End a claimed episode as a worker files it (its replay not verified)."""
    filing = Filing(
        status="finished",
        outcome=outcome,
        reason=f"{outcome} at tick 9",
        data_digest=f"{trial_id:064x}",
        metrics={"reward": reward},
    )
    assert server.lab.service.queue.finish(trial_id, "w", filing)


def file(server: ServerThread, trials: list[int], outcomes: list[str]) -> None:
    for n, (trial_id, outcome) in enumerate(zip(trials, outcomes, strict=True)):
        claim(server, trial_id)
        finish(server, trial_id, outcome, n / 16)  # sixteenths: ties to round (0.0625 ...)


def shot(watched: Watched, name: str) -> None:
    SHOTS.mkdir(parents=True, exist_ok=True)
    watched.page.screenshot(path=str(SHOTS / f"{name}.png"), full_page=True)


def counts(page) -> dict[str, str]:
    return page.eval_on_selector_all(
        "[data-count]",
        "nodes => Object.fromEntries(nodes.map(n => [n.dataset.count, n.textContent]))",
    )


def test_an_evaluation_page_follows_its_episodes_then_compares(server, repo, watched: Watched):
    """While its episodes are filed, the open page updates its counts, cells and score
    from the API, with no reload, until it reads as the page reloaded; then "Compare
    with…" pairs it with another evaluation and shows the API's sentence, and the task's
    page ranks the two, tied."""
    service = server.lab.service
    service.index.add_user("erin", max_daily=500)
    first = evaluated(server, "main", repo)
    trials = [r.trial for r in service.evaluations.get(first).rows]
    page = watched.page
    page.goto(server.http_url(f"/evaluations/{first}"))
    assert page.locator("#status").inner_text().lower() == "queued"
    assert counts(page)["queued"] == "20"
    page.evaluate("() => { window.sameDocument = true; }")  # gone, were the page reloaded

    file(server, trials[:6], OUTCOMES[:6])
    claim(server, trials[6])
    page.wait_for_function(
        "document.querySelector('[data-count=success]').textContent === '6'"
        " && document.querySelector('[data-count=running]').textContent === '1'",
        timeout=20 * MS,
    )
    assert counts(page) == {
        "success": "6",
        "fail": "0",
        "error": "0",
        "running": "1",
        "queued": "13",
        "cancelled": "0",
    }
    assert page.locator("#status").inner_text().lower() == "running"
    assert page.locator("[data-episode='6']").get_attribute("class") == "cell running"
    assert page.locator("#rate").inner_text() == "6 of 20 episodes ended so far, 6 succeeded"
    shot(watched, "evaluation-running")

    finish(server, trials[6], OUTCOMES[6], 6 / 16)
    file(server, trials[7:], OUTCOMES[7:])
    page.wait_for_function(
        "document.getElementById('evaluation').dataset.status === 'finished'", timeout=20 * MS
    )
    assert page.evaluate("() => window.sameDocument") is True
    assert counts(page)["error"] == "3" and counts(page)["fail"] == "5"
    assert page.locator("#following").is_hidden()
    followed = page.locator("#evaluation").inner_text()
    cells = page.eval_on_selector_all(
        "[data-episode]", "cells => cells.map(c => [c.className, c.title])"
    )
    shot(watched, "evaluation")
    page.reload()
    assert page.evaluate("() => window.sameDocument") is None
    assert page.locator("#evaluation").inner_text() == followed  # the same words, rounded alike
    assert (
        page.eval_on_selector_all(
            "[data-episode]", "cells => cells.map(c => [c.className, c.title])"
        )
        == cells
    )
    assert "60 % (" in page.locator("#rate").inner_text()

    second = evaluated(server, "v1", repo)
    later = [r.trial for r in service.evaluations.get(second).rows]
    file(server, later, ["success"] * 16 + ["fail"] * 4)
    page.click("#compare")
    page.wait_for_url(f"**/compare?a={first}")
    page.select_option("#b", str(second))
    page.click("#choose button[type=submit]")
    page.wait_for_url(f"**/compare?a={first}&b={second}")
    compared = compare(service.evaluations.get(first), service.evaluations.get(second))
    assert page.locator("#said").inner_text() == compared.said
    assert page.locator("#only-b").inner_text() == "4"
    shot(watched, "compare")

    verify_episodes(service, trials + later)  # as the lab's replays would: now they rank
    page.click("h1 a")  # the task
    page.wait_for_url("**/tasks/icreate-maze")
    ranked = page.eval_on_selector_all(
        "tr[data-evaluation]", "rows => rows.map(r => Number(r.dataset.evaluation))"
    )
    assert ranked == [second, first]
    assert page.locator("tr[data-evaluation] .tie").count() == 1  # 80 % and 60 % overlap
    shot(watched, "task-leaderboard")
    watched.check()
