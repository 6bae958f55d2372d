"""The matches' pages in process: a match's page (its teams, the score in legs, what it
adds up to, its replays, a row per leg linked to its trial) as it is played, the list of
matches, a task's ladder (and the 404 of a task without sides), the task and trial pages'
links to them. (tests/integration/test_match_pages_browser.py follows a match in
Chromium.)

Matches are submitted through the API to real git repositories; no workers run, so legs
are claimed and filed the way a worker files them, their result in their metrics from the
sides' view (``scheduler.outcome.judge_leg``).
"""

# ruff: noqa: F811 (the API's fixtures, imported from test_api, are the tests' arguments)
from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
from markupsafe import escape

from labd.web.evaluations import DASH
from repository.index import Derived
from repository.trial import Filing
from repository.well_known import REPLAY, VIDEO
from tests.fakes import verify_episodes
from tests.helpers.githttp import GitRepo
from tests.labd.test_api import auth, service  # noqa: F401 (fixtures)
from tests.labd.test_web_evaluations import Elements, web, writer  # noqa: F401 (fixtures)

HTML_NAME = "<b>bold</b> & co"  # a repository's directory: the pages show it, never parse it
TOML = '[controller]\ncommand = ["python", "c.py"]\n'


@pytest.fixture
def teams(tmp_path) -> tuple[Path, Path]:
    """Two teams' repositories, B's directory named with HTML in it."""
    a = GitRepo.create(tmp_path / "alpha", {"lab.toml": TOML, "c.py": "print('a')\n"})
    b = GitRepo.create(tmp_path / HTML_NAME, {"lab.toml": TOML, "c.py": "print('b')\n"})
    return a.path, b.path


async def played(web, token, a: Path, b: Path, seeds: int = 2) -> dict[str, Any]:
    reply = await web.post(
        "/api/matches",
        json={
            "task": "soccer-1v1",
            "seeds": seeds,
            "a": {"repository": str(a)},
            "b": {"repository": str(b)},
        },
        headers=auth(token),
    )
    assert reply.status_code == 201, reply.text
    return reply.json()


def result(winner: str, ended_by: str, home: int, away: int, forfeited: str = "") -> dict[str, Any]:
    """A leg's metrics as the leg runner files them (the sides' view)."""
    return {
        "winner": winner,
        "ended_by": ended_by,
        "forfeited": forfeited,
        "home_goals": home,
        "away_goals": away,
    }


def file_legs(service, results: dict[int, dict[str, Any] | None]) -> None:
    """Claim queued legs and file each trial in ``results`` as a worker would: a result
    (a success), or None for an error (no result)."""
    service.queue.check = None  # the filings here name no record file
    left = dict(results)
    while left:
        claim = service.queue.claim("w")
        assert claim is not None, f"legs {sorted(left)} were never claimed"
        if claim.id not in left:
            service.queue.release_worker("w")
            continue
        metrics = left.pop(claim.id)
        filing = Filing(
            status="finished",
            outcome="success" if metrics is not None else "error",
            reason="played" if metrics is not None else "every side forfeited",
            data_digest=f"{claim.id:064x}",
            metrics=metrics or {},
        )
        assert service.queue.finish(claim.id, "w", filing)


def legs_of(match: dict[str, Any]) -> list[int]:
    return [leg["trial"] for leg in match["legs"]]


def rows(page: Elements) -> list[dict[str, str]]:
    return [e for e in page.found if e["tag"] == "tr" and "data-leg" in e]


def parts(page: Elements, name: str) -> list[str]:
    return [e["text"] for e in page.found if e.get("data-part") == name]


async def test_a_match_page_shows_the_teams_the_score_and_every_leg(web, service, writer, teams):
    """Queued, the page says how far the match is and follows it; finished, it shows
    each team with its commit linked, the score in legs (A's wins, B's wins, draws) and
    who won the match, a row per leg (seed, home, goals A-B, who won and how, its replay,
    its trial), whether every counted leg verified and whether it counts on the ladder; a
    repository named with HTML is shown as text."""
    a, b = teams
    m = await played(web, writer, a, b)
    queued = Elements((await web.get(f"/matches/{m['id']}")).text)
    assert queued.by_id("status")["text"] == "queued"
    assert queued.by_id("score-said")["text"] == "0 of 4 legs ended so far"
    assert queued.by_id("signed")["text"] == "signed by the lab when every leg has ended"
    assert queued.by_id("step-deadline")["text"].startswith("10 s (a team that keeps")
    assert not queued.by_id("following").get("hidden")
    assert [e["text"] for e in queued.found if e.get("data-part") == "state"] == ["queued"] * 4

    legs = legs_of(m)
    assert [leg["home"] for leg in m["legs"]] == ["a", "b", "a", "b"]
    file_legs(
        service,
        {
            legs[0]: result("home", "goal", 1, 0),  # A at home scores
            legs[1]: result("away", "goal", 0, 2),  # A away scores twice
            legs[2]: result("draw", "time", 0, 0),
        },
    )
    part_way = Elements((await web.get(f"/matches/{m['id']}")).text)
    assert part_way.by_id("status")["text"] == "running"
    assert part_way.by_id("score-said")["text"] == "3 of 4 legs ended so far"
    assert part_way.by_id("verified")["text"] == (
        "not verified: 0 of 3 counted legs replayed identically; 3 not replayed yet"
    )
    file_legs(service, {legs[3]: result("away", "forfeit", 0, 0, forfeited="home")})
    verify_episodes(service, legs)

    reply = await web.get(f"/matches/{m['id']}")
    assert reply.status_code == 200
    page = Elements(reply.text)
    api = (await web.get(f"/api/matches/{m['id']}")).json()
    assert api["score"] == {"a": 3, "b": 0, "draws": 1} and api["verified"] is True
    assert page.by_id("status")["text"] == "finished"
    [h1] = [e for e in page.found if e["tag"] == "h1"]
    assert h1["text"] == f"Match {m['id']}: soccer-1v1"
    assert [page.by_id(f"score-{s}")["text"] for s in ("a", "b", "draws")] == ["3", "0", "1"]
    assert page.by_id("score-said")["text"] == f"A won the match, 3{DASH}0 with 1 draw"
    assert page.by_id("verified")["text"] == "✓ verified: all 4 counted legs replayed identically"
    assert page.by_id("verified")["class"] == "reproduced"
    assert page.by_id("ladder-said")["text"] == "counts on the ladder"
    assert page.by_id("signed")["text"].startswith("signed by the lab (key ed25519:")
    assert page.by_id("following").get("hidden") == ""
    assert [r["data-leg"] for r in rows(page)] == ["0", "1", "2", "3"]
    assert parts(page, "goals") == [f"1{DASH}0", f"2{DASH}0", f"0{DASH}0", f"0{DASH}0"]
    assert parts(page, "result") == [
        "A won on goals",
        "A won on goals",
        "draw at time",
        "A won by forfeit (B forfeited)",
    ]
    assert parts(page, "verdict") == ["✓ verified"] * 4
    assert parts(page, "state") == ["success"] * 4
    homes = [r["text"].split()[2] for r in rows(page)]  # leg, seed, home
    assert homes == ["A", "B", "A", "B"]
    links = [e["href"] for e in page.having("href")]
    assert all(f"/trials/{t}" in links for t in legs)
    assert f"/commits/{m['a']['commit']}" in links and f"/commits/{m['b']['commit']}" in links
    assert "/ladders/soccer-1v1" in links and "/tasks/soccer-1v1" in links
    assert "/static/match.js" in reply.text
    assert page.by_id("videos-note")["text"].startswith("No leg's video is rendered yet")
    assert HTML_NAME not in reply.text and str(escape(HTML_NAME)) in reply.text
    assert page.by_id("team-b")["text"].count(HTML_NAME) == 2  # as text: its name and path

    leg = Elements((await web.get(f"/trials/{legs[1]}")).text).by_id("match")
    assert leg["text"].startswith(f"A leg of match {m['id']} (seed 0): this commit played home")
    assert f"{a}@{m['a']['commit'][:10]} away" in leg["text"]  # B at home, A away


async def test_a_leg_without_a_result_and_a_diverged_replay_keep_a_match_off_the_ladder(
    web, service, writer, teams
):
    """A leg that ended without a result counts for no one and is said to; a counted leg
    whose replay diverged is named, and keeps the match off the ladder; a leg whose video
    the lab has rendered has it embedded, the others are left to their trials' pages."""
    a, b = teams
    m = await played(web, writer, a, b, seeds=1)
    legs = legs_of(m)
    file_legs(service, {legs[0]: result("away", "goal", 0, 1), legs[1]: None})
    page = Elements((await web.get(f"/matches/{m['id']}")).text)
    assert page.by_id("score-said")["text"] == (
        f"B won the match, 0{DASH}1 with 0 draws; 1 of 2 legs without a result"
    )
    assert parts(page, "result") == ["B won on goals", "-"]
    assert parts(page, "state") == ["success", "error"]
    assert parts(page, "verdict") == ["not yet", "-"]
    assert page.by_id("ladder-said")["text"] == (
        "not on the ladder until every counted leg's replay has verified"
    )
    service.index.put_derived(legs[0], diverged(service))
    page = Elements((await web.get(f"/matches/{m['id']}")).text)
    assert page.by_id("verified")["text"] == (
        "not verified: 0 of 1 counted leg replayed identically; 1 diverged (leg 0)"
    )
    assert parts(page, "verdict") == ["diverged", "-"]

    film = service.store.put_bytes(b"not really an mp4")  # the lab rendered leg 0's video
    service.index.put_derived(legs[0], Derived(VIDEO, film, 17, "video/mp4"))
    page = Elements((await web.get(f"/matches/{m['id']}")).text)
    videos = [e for e in page.found if e["tag"] == "video"]
    assert [v["src"] for v in videos] == [f"/api/trials/{legs[0]}/video"]
    assert page.by_id("videos-note")["text"].startswith("The other legs' videos are")


def diverged(service):
    """A replay verdict that says the leg's record did not come back identical."""
    verdict = b'{"verified": false}'
    return Derived(REPLAY, service.store.put_bytes(verdict), len(verdict), "application/json")


async def test_a_missing_match_is_a_404_page(web):
    """An unknown match is the API's 404, as a page."""
    reply = await web.get("/matches/424242", headers={"Accept": "text/html"})
    assert reply.status_code == 404 and reply.headers["content-type"].startswith("text/html")
    assert "<h1>No match 424242</h1>" in reply.text


async def test_the_ladder_ranks_commits_with_their_intervals(web, service, writer, teams):
    """The ladder lists the API's rows in its order, each rating with its 95 % interval
    in words and as a bar, its matches and legs won, lost and drawn, and says how it is
    computed; the list of matches has the match; the task page links the ladder."""
    a, b = teams
    m = await played(web, writer, a, b)
    legs = legs_of(m)
    file_legs(
        service,
        {
            legs[0]: result("home", "goal", 1, 0),
            legs[1]: result("away", "goal", 0, 1),
            legs[2]: result("draw", "time", 0, 0),
            legs[3]: result("home", "goal", 1, 0),  # B at home wins
        },
    )
    verify_episodes(service, legs)
    api = (await web.get("/api/ladders/soccer-1v1")).json()["rows"]
    reply = await web.get("/ladders/soccer-1v1")
    assert reply.status_code == 200
    page = Elements(reply.text)
    shown = [e for e in page.found if e["tag"] == "tr" and "data-commit" in e]
    assert [r["data-commit"] for r in shown] == [r["commit"] for r in api]
    top = api[0]
    assert top["repository"] == str(a) and (top["wins"], top["losses"], top["draws"]) == (2, 1, 1)
    low, high = top["interval"]
    assert f"{top['rating']:.0f} ({low:.0f}{DASH}{high:.0f})" in shown[0]["text"]
    assert f"2{DASH}1{DASH}1" in shown[0]["text"] and f"1{DASH}2{DASH}1" in shown[1]["text"]
    assert all("provisional" in r["text"] for r in shown)  # one match each, under three
    bars = [e for e in page.found if e["tag"] == "svg"]
    assert len(bars) == 2 and f"95 % interval {low:.0f}{DASH}{high:.0f}" in bars[0]["aria-label"]
    how = page.by_id("how")["text"]
    assert "Bradley-Terry" in how and "a draw counts half" in how and "bootstrap" in how
    assert str(escape(HTML_NAME)) in reply.text and HTML_NAME not in reply.text
    assert f"/matches/{m['id']}" in reply.text  # its latest matches

    listed = Elements((await web.get("/matches?task=soccer-1v1")).text)
    assert [e["data-match"] for e in listed.having("data-match")] == [str(m["id"])]
    assert f"A won the match, 2{DASH}1 with 1 draw" in listed.having("data-match")[0]["text"]
    task = Elements((await web.get("/tasks/soccer-1v1")).text)
    assert task.by_id("ladder-link")["href"] == "/ladders/soccer-1v1"


async def test_an_empty_ladder_says_how_to_play_and_a_task_without_sides_has_none(web):
    """A ladder without matches says so and how to play one; a task two teams do not
    play has no ladder: a 404 page saying which tasks have one; its task page has no
    link to one."""
    empty = Elements((await web.get("/ladders/soccer-2v2")).text).by_id("empty")
    assert empty["text"].startswith("No one is on this ladder yet")
    assert "labd match REPO_A REPO_B --task soccer-2v2" in empty["text"]
    assert "POST /api/matches" in empty["text"]

    none = await web.get("/ladders/icreate-maze", headers={"Accept": "text/html"})
    assert none.status_code == 404 and none.headers["content-type"].startswith("text/html")
    assert "<h1>No ladder</h1>" in none.text
    assert "icreate-maze is not played by two teams" in none.text
    assert "soccer-1v1, soccer-2v2" in none.text
    unknown = await web.get("/ladders/no-such-task", headers={"Accept": "text/html"})
    assert unknown.status_code == 404
    maze = Elements((await web.get("/tasks/icreate-maze")).text)
    assert not [e for e in maze.found if e.get("id") == "ladder-link"]
    assert "No matches yet" in (await web.get("/matches")).text


async def test_the_robots_page_lists_the_matches_under_way(web, service, writer, teams):
    """A match queued or being played is on the robots page, with its legs played so far
    and its score, linked to its page; once every leg has ended it leaves the list."""
    a, b = teams
    robots = Elements((await web.get("/robots")).text)
    assert not robots.having("data-match")
    m = await played(web, writer, a, b, seeds=1)
    listed = Elements((await web.get("/robots")).text)
    [row] = listed.having("data-match")
    assert row["data-match"] == str(m["id"]) and row["text"].split()[:2] == ["match", str(m["id"])]
    assert "0 of 2 played" in row["text"]
    assert HTML_NAME in row["text"]  # B's folder, named with HTML, shown as text
    legs = legs_of(m)
    file_legs(service, {legs[0]: result("home", "goal", 1, 0)})
    [row] = Elements((await web.get("/robots")).text).having("data-match")
    assert "1 of 2 played · playing" in " ".join(row["text"].split())
    assert "A 1, B 0, 0 drawn" in row["text"]
    file_legs(service, {legs[1]: result("draw", "time", 0, 0)})
    assert not Elements((await web.get("/robots")).text).having("data-match")
