"""A match's pages in a real browser (Debian's Chromium), against a real lab.

The lab runs no worker: the test files the legs the way a worker does, while the
match's page is open, and the page follows them through the API without reloading
until it reads as the page reloaded; then the task's ladder ranks the teams of two
matches, each rating's interval drawn as a bar.
"""

# ruff: noqa: F811 (the fixture imported from the evaluation pages' test is the tests' argument)
from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from labd.web.evaluations import DASH
from repository.trial import Filing
from scheduler.matches import MatchRequest, TeamRequest
from tests.fakes import verify_episodes
from tests.helpers.githttp import GitRepo
from tests.helpers.labs import ServerThread
from tests.integration.browser import Watched, browser, watched
from tests.integration.test_evaluation_pages_browser import server  # noqa: F401 (a fixture)

__all__ = ["browser", "watched"]
pytestmark = [pytest.mark.integration, pytest.mark.timeout(180)]
SHOTS = Path(__file__).resolve().parents[2] / "build" / "screenshots"
MS = 1000
TOML = '[controller]\ncommand = ["python", "c.py"]\n'
HTML_NAME = "<b>bold</b> & co"  # a team's directory: shown as text


def team(path: Path, says: str) -> str:
    return str(GitRepo.create(path, {"lab.toml": TOML, "c.py": f"print({says!r})\n"}).path)


def matched(server: ServerThread, a: str, b: str) -> int:
    service = server.lab.service
    user = service.index.user("erin")
    request = MatchRequest(
        task="soccer-1v1", seeds=2, a=TeamRequest(repository=a), b=TeamRequest(repository=b)
    )
    return service.matchmaker.submit(user, request)


def claim(server: ServerThread, trial_id: int) -> None:
    service = server.lab.service
    service.queue.check = None  # the filings below name no record
    claimed = service.queue.claim("w")
    assert claimed is not None and claimed.id == trial_id


def finish(server: ServerThread, trial_id: int, metrics: dict[str, Any]) -> None:
    """End a claimed leg as a worker files it, its result in its metrics (not verified)."""
    filing = Filing(
        status="finished",
        outcome="success",
        reason=f"{metrics['winner']} at tick 399",
        data_digest=f"{trial_id:064x}",
        metrics=metrics,
    )
    assert server.lab.service.queue.finish(trial_id, "w", filing)


def result(winner: str, ended_by: str, home: int, away: int, forfeited: str = "") -> dict[str, Any]:
    return {
        "winner": winner,
        "ended_by": ended_by,
        "forfeited": forfeited,
        "home_goals": home,
        "away_goals": away,
    }


def play(server: ServerThread, legs: list[int], results: list[dict[str, Any]]) -> None:
    for trial_id, metrics in zip(legs, results, strict=True):
        claim(server, trial_id)
        finish(server, trial_id, metrics)


def shot(watched: Watched, name: str) -> None:
    SHOTS.mkdir(parents=True, exist_ok=True)
    watched.page.screenshot(path=str(SHOTS / f"{name}.png"), full_page=True)


def parts(page: Any, name: str) -> list[str]:
    return page.eval_on_selector_all(
        f"[data-part={name}]", "nodes => nodes.map(n => n.textContent)"
    )


def test_a_match_page_follows_its_legs_then_the_ladder_ranks_the_teams(
    server, tmp_path, watched: Watched
):
    """While its legs are filed, the open page updates its score, words and rows from
    the API, with no reload, until it reads as the page reloaded; a team named with HTML
    shows as text; the ladder ranks the three teams of two matches, with bars."""
    service = server.lab.service
    service.index.add_user("erin", max_daily=500)
    alpha = team(tmp_path / "alpha-chaser", "alpha")
    bold = team(tmp_path / HTML_NAME, "bold")
    still = team(tmp_path / "still-keeper", "still")
    first = matched(server, alpha, bold)
    legs = [leg.trial for leg in service.matches.get(first).legs]
    page = watched.page
    page.goto(server.http_url(f"/matches/{first}"))
    assert page.locator("#status").inner_text().lower() == "queued"
    assert page.locator("#team-b .repo-name").inner_text() == bold  # text, not markup
    page.evaluate("() => { window.sameDocument = true; }")  # gone, were the page reloaded

    play(server, legs[:2], [result("home", "goal", 1, 0), result("home", "goal", 1, 0)])
    claim(server, legs[2])
    page.wait_for_function(
        "document.getElementById('score-said').textContent === '2 of 4 legs ended so far'"
        " && document.querySelector('[data-leg=\"2\"] [data-part=state]').textContent"
        " === 'running'",
        timeout=20 * MS,
    )
    assert page.locator("#status").inner_text().lower() == "running"
    assert [page.locator(f"#score-{s}").inner_text() for s in ("a", "b", "draws")] == [
        "1",
        "1",
        "0",
    ]
    assert parts(page, "result") == ["A won on goals", "B won on goals", "-", "-"]
    shot(watched, "match-running")

    finish(server, legs[2], result("home", "goal", 2, 0))
    play(server, legs[3:], [result("draw", "time", 0, 0)])
    verify_episodes(service, legs)
    page.wait_for_function(
        "document.getElementById('match').dataset.status === 'finished'", timeout=20 * MS
    )
    assert page.evaluate("() => window.sameDocument") is True
    assert page.locator("#following").is_hidden()
    assert page.locator("#score-said").inner_text() == f"A won the match, 2{DASH}1 with 1 draw"
    followed = page.locator("#match").inner_text()
    page.reload()
    assert page.evaluate("() => window.sameDocument") is None
    assert page.locator("#match").inner_text() == followed  # the same words, reloaded
    assert page.locator("#verified").inner_text() == (
        "✓ verified: all 4 counted legs replayed identically"
    )
    shot(watched, "match")

    second = matched(server, alpha, still)
    later = [leg.trial for leg in service.matches.get(second).legs]
    forfeit = result("home", "forfeit", 0, 0, forfeited="away")
    play(server, later, [forfeit, result("away", "forfeit", 0, 0, forfeited="home")] * 2)
    verify_episodes(service, later)
    page.click("a[href='/ladders/soccer-1v1']")
    page.wait_for_url("**/ladders/soccer-1v1")
    ranked = page.eval_on_selector_all(
        "tr[data-commit]", "rows => rows.map(r => r.querySelector('.repo').title)"
    )
    assert ranked[0] == alpha and set(ranked[1:]) == {bold, still}
    assert page.locator("tr[data-commit] svg .interval").count() == 3
    shot(watched, "ladder")

    page.goto(server.http_url("/matches"))
    assert page.locator("tr[data-match]").count() == 2
    shot(watched, "matches")
    page.goto(server.http_url(f"/trials/{legs[1]}"))
    assert page.locator("#match").inner_text().startswith(f"A leg of match {first} (seed 0)")
    watched.check()
