"""Matches through the HTTP API in process: a match queues each seed twice with the
sides swapped, its legs are filed the way a worker files them, its score and signature
follow; a leg is never cancelled alone; the ladder rates the commits of finished,
verified matches; a commit joining the ladder is given its matches.

No workers run here: legs are claimed and filed as a worker files them, their result in
their metrics as the leg runner writes it.
"""

# ruff: noqa: F811 (the API's fixtures, imported from test_api, are the tests' arguments)
from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from repository.trial import Filing
from scheduler.matches import LadderBudget
from tests.fakes import verify_episodes
from tests.helpers.githttp import GitRepo
from tests.labd.test_api import api, auth, service, token  # noqa: F401 (fixtures)

LAB_TOML = '[controller]\ncommand = ["python", "c.py"]\ntask = "soccer-1v1"\n'


def team(tmp_path: Path, name: str) -> str:
    return str(GitRepo.create(tmp_path / name, {"lab.toml": LAB_TOML, "c.py": f"# {name}\n"}).path)


async def play(api: Any, token: str, a: str, b: str, seeds: int = 1) -> Any:
    return await api.post(
        "/api/matches",
        json={"task": "soccer-1v1", "a": {"repository": a}, "b": {"repository": b}, "seeds": seeds},
        headers=auth(token),
    )


def file_legs(service: Any, winner: dict[int, str]) -> None:
    """Claim the queued legs and file each trial in ``winner`` (trial -> the side that
    won: home, away or draw), as a worker would; its replay verified."""
    service.queue.check = None
    left = dict(winner)
    while left:
        claim = service.queue.claim("w")
        assert claim is not None, f"legs {sorted(left)} were never claimed"
        side = left.pop(claim.id)
        goals = {"home": int(side == "home"), "away": int(side == "away")}
        filing = Filing(
            status="finished",
            outcome="success",
            reason=f"{side} at tick 9",
            data_digest=f"{claim.id:064x}",
            metrics={
                "winner": side,
                "ended_by": "goal" if side != "draw" else "time",
                "forfeited": "",
                "home_goals": goals["home"],
                "away_goals": goals["away"],
            },
        )
        assert service.queue.finish(claim.id, "w", filing)
        verify_episodes(service, [claim.id])


async def test_a_match_plays_each_seed_twice_and_is_scored_and_signed(
    api, service, token, tmp_path
):
    a, b = team(tmp_path, "mover"), team(tmp_path, "still")
    reply = await play(api, token, a, b, seeds=2)
    assert reply.status_code == 201, reply.text
    match = reply.json()
    assert reply.headers["location"].endswith(f"/api/matches/{match['id']}")
    assert [(leg["seed"], leg["home"]) for leg in match["legs"]] == [
        (0, "a"), (0, "b"), (1, "a"), (1, "b")
    ]  # fmt: skip
    assert (match["status"], match["score"]) == ("queued", {"a": 0, "b": 0, "draws": 0})
    assert match["step_deadline"] == 10.0  # the lab's default
    legs = [(await api.get(f"/api/trials/{leg['trial']}")).json() for leg in match["legs"]]
    assert [t["kind"] for t in legs] == ["match"] * 4
    assert [(t["repository"], t["away"]["repository"]) for t in legs] == [(a, b), (b, a)] * 2
    assert {t["commit"] for t in legs} == {match["a"]["commit"], match["b"]["commit"]}

    trials = [leg["trial"] for leg in match["legs"]]
    # A wins at home on seed 0 and away on seed 0 (B at home lost), draws seed 1 twice
    file_legs(service, dict(zip(trials, ["home", "away", "draw", "draw"], strict=True)))
    done = (await api.get(f"/api/matches/{match['id']}")).json()
    assert done["status"] == "finished" and done["verified"] is True
    assert done["score"] == {"a": 2, "b": 0, "draws": 2}
    assert [leg["result"] for leg in done["legs"]] == ["a", "a", "draw", "draw"]
    assert done["legs"][1]["goals"] == {"a": 1, "b": 0}  # A scored away
    statement = done["signature"]["statement"]
    assert statement["schema"] == "labd.match/1" and statement["score"] == done["score"]
    assert [leg["data_digest"] for leg in statement["legs"]] == [f"{t:064x}" for t in trials]

    listed = (await api.get("/api/matches", params={"commit": match["b"]["commit"][:8]})).json()
    assert [m["id"] for m in listed["matches"]] == [match["id"]]
    ladder = (await api.get("/api/ladders/soccer-1v1")).json()
    assert [r["repository"] for r in ladder["rows"]] == [a, b]
    top = ladder["rows"][0]
    assert (top["wins"], top["losses"], top["draws"], top["matches"]) == (2, 0, 2, 1)
    assert top["provisional"] is True and top["interval"][0] <= top["rating"]


async def test_a_leg_is_cancelled_only_with_its_match_which_then_counts_for_no_one(
    api, service, token, tmp_path
):
    a, b = team(tmp_path, "a"), team(tmp_path, "b")
    match = (await play(api, token, a, b)).json()
    leg = match["legs"][0]["trial"]
    alone = await api.post(f"/api/trials/{leg}/cancel", headers=auth(token))
    assert alone.status_code == 409
    assert f"trial {leg} is a leg of match {match['id']}" in alone.json()["error"]
    other = service.index.add_user("bob")
    refused = await api.post(f"/api/matches/{match['id']}/cancel", headers=auth(other))
    assert refused.status_code == 403
    cancelled = await api.post(f"/api/matches/{match['id']}/cancel", headers=auth(token))
    assert cancelled.status_code == 200, cancelled.text
    assert cancelled.json()["status"] == "cancelled"
    assert {leg["status"] for leg in cancelled.json()["legs"]} == {"cancelled"}
    assert (await api.get("/api/ladders/soccer-1v1")).json()["rows"] == []


async def test_a_match_s_step_deadline_reaches_its_legs(api, service, token, tmp_path):
    a, b = team(tmp_path, "a"), team(tmp_path, "b")
    reply = await api.post(
        "/api/matches",
        json={
            "task": "soccer-1v1",
            "a": {"repository": a},
            "b": {"repository": b},
            "seeds": 1,
            "step_deadline": 4,
        },
        headers=auth(token),
    )
    assert reply.status_code == 201, reply.text
    match = reply.json()
    assert match["step_deadline"] == 4.0
    for leg in match["legs"]:
        assert (await api.get(f"/api/trials/{leg['trial']}")).json()["step_deadline"] == 4.0
    claim = service.queue.claim("w")
    assert claim is not None and claim.order.step_deadline == 4.0
    assert claim.order.rerun(claim.id).step_deadline == 4.0  # a rerun keeps it
    too_long = await api.post(
        "/api/matches",
        json={"task": "soccer-1v1", "a": {"repository": a}, "b": {"repository": b},
              "step_deadline": 61},
        headers=auth(token),
    )  # fmt: skip
    assert too_long.status_code == 422


async def test_what_is_no_match_is_refused_in_words(api, token, tmp_path):
    a = team(tmp_path, "a")
    maze = await api.post(
        "/api/matches",
        json={"task": "icreate-maze", "a": {"repository": a}, "b": {"repository": a}},
        headers=auth(token),
    )
    assert maze.status_code == 422, maze.text  # an InvalidRequest, as a bad parameter
    assert "icreate-maze is not played by two teams" in maze.json()["error"]
    unknown = await play(api, token, a, str(tmp_path / "nowhere"))
    assert unknown.status_code == 422 and "could not be fetched" in unknown.text
    too_many = await play(api, token, a, a, seeds=51)
    assert too_many.status_code == 422
    assert (await api.get("/api/ladders/icreate-maze")).status_code == 404
    assert (await api.get("/api/matches/99")).status_code == 404


async def test_a_commit_joining_the_ladder_is_given_its_matches(api, service, token, tmp_path):
    """The first entry waits; each next one plays the entered commits with the fewest
    matches and those rated nearest it, three at most; a user enters a few a day."""
    teams = [team(tmp_path, f"t{n}") for n in range(5)]
    joined = []
    for repository in teams:
        reply = await api.post(
            "/api/ladders/soccer-1v1/entries",
            json={"repository": repository},
            headers=auth(token),
        )
        assert reply.status_code == 201, reply.text
        joined.append(reply.json())
    counts = [len(j["matches"]) for j in joined]
    assert counts == [0, 1, 2, 3, 3]
    for j, repository in zip(joined, teams, strict=True):
        assert {m["a"]["repository"] for m in j["matches"]} <= {repository}
        assert all(len(m["legs"]) == 2 for m in j["matches"])
    # every entry had 3 matches when t4 joined, all unrated: the earlier entries first
    assert [m["b"]["repository"] for m in joined[4]["matches"]] == teams[:3]
    service.matchmaker.budget = LadderBudget(per_day=5)
    over = await api.post(
        "/api/ladders/soccer-1v1/entries",
        json={"repository": team(tmp_path, "t5")},
        headers=auth(token),
    )
    assert over.status_code == 429, over.text
    assert "entered 5 commits on ladders in the last 24 hours" in over.json()["error"]


@pytest.mark.parametrize("task", ["icreate-maze", "no-such-task"])
async def test_only_a_task_teams_play_has_a_ladder_to_join(api, token, tmp_path, task):
    reply = await api.post(
        f"/api/ladders/{task}/entries",
        json={"repository": team(tmp_path, "a")},
        headers=auth(token),
    )
    assert reply.status_code in (404, 422), reply.text
