"""Matches on a real lab (its HTTP API, one bubblewrap worker): the example ball chaser
against a team that connects and never steps wins every leg by forfeit, each seed
played twice with the sides swapped, without the match stalling; against another
commit of the chaser every leg is played; every leg is filed, replayed, verified and
the match signed; the ladder rates the chaser above the team that forfeits, with
intervals; a leg is never cancelled alone."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import httpx
import pytest

from scheduler.runner import RunOptions
from tests.helpers.githttp import GitRepo
from tests.helpers.labs import lab_config, running
from tests.integration.test_match_leg import STILL

pytestmark = [pytest.mark.integration, pytest.mark.timeout(600)]
ROOT = Path(__file__).resolve().parents[2]
CHASER = ROOT / "controllers" / "examples" / "soccer-chaser"
WAIT = 300.0


def repo(path: Path, files: dict[str, str]) -> str:
    return str(GitRepo.create(path, files, "a team").path)


def finished(client: httpx.Client, match_id: int) -> dict[str, Any]:
    """The match once it has ended and every leg with a result has its replay's verdict."""
    deadline = time.monotonic() + WAIT
    while time.monotonic() < deadline:
        match = client.get(f"/api/matches/{match_id}").json()
        counted = [leg for leg in match["legs"] if leg["result"] is not None]
        if match["status"] == "finished" and all(leg["verified"] is not None for leg in counted):
            return match
        time.sleep(0.5)
    raise AssertionError(f"match {match_id} did not end within {WAIT:g} s: {match}")


def test_a_mover_beats_a_team_that_never_steps_and_tops_the_ladder(cache, tmp_path):
    chaser_files = {p.name: p.read_text() for p in CHASER.iterdir() if p.is_file()}
    chaser = repo(tmp_path / "chaser", chaser_files)
    rival = repo(tmp_path / "rival", {**chaser_files, "README.md": "the same chaser, again\n"})
    still = repo(
        tmp_path / "still",
        {"lab.toml": '[controller]\ncommand = ["python", "still.py"]\n', "still.py": STILL},
    )
    run = RunOptions(first_step=15.0)  # the chaser's margin beside a busy lab
    config = lab_config(tmp_path / "data", (), workers=1, cache=cache, service={"run": run})
    with running(config) as server:
        service = server.lab.service
        token = service.index.add_user("alice", max_daily=100)
        headers = {"Authorization": f"Bearer {token}"}
        with httpx.Client(base_url=server.http_url(), headers=headers, timeout=30) as client:
            asked = {"task": "soccer-1v1", "seeds": 1}
            made = client.post(
                "/api/matches",
                json={**asked, "a": {"repository": chaser}, "b": {"repository": still}},
            )
            assert made.status_code == 201, made.text
            forfeit = made.json()
            assert [(leg["seed"], leg["home"]) for leg in forfeit["legs"]] == [(0, "a"), (0, "b")]
            leg = forfeit["legs"][0]["trial"]
            refused = client.post(f"/api/trials/{leg}/cancel")
            assert refused.status_code == 409, refused.text
            assert f"a leg of match {forfeit['id']}" in refused.json()["error"]

            played = client.post(
                "/api/matches",
                json={**asked, "a": {"repository": chaser}, "b": {"repository": rival}},
            ).json()

            forfeit = finished(client, forfeit["id"])
            assert forfeit["score"] == {"a": 2, "b": 0, "draws": 0}, forfeit["legs"]
            assert [leg["reason"] for leg in forfeit["legs"]] == ["forfeit", "forfeit"]
            assert [leg["forfeited"] for leg in forfeit["legs"]] == [["b"], ["b"]]
            assert forfeit["verified"] is True, forfeit["legs"]
            assert forfeit["signature"]["statement"]["schema"] == "labd.match/1"
            home_then_away = [
                client.get(f"/api/trials/{leg['trial']}").json() for leg in forfeit["legs"]
            ]
            assert [t["repository"] for t in home_then_away] == [chaser, still]
            assert [t["away"]["repository"] for t in home_then_away] == [still, chaser]

            played = finished(client, played["id"])
            assert all(leg["result"] is not None for leg in played["legs"]), played["legs"]
            assert all(leg["reason"] in ("goal", "time") for leg in played["legs"])
            assert played["verified"] is True
            for leg in forfeit["legs"] + played["legs"]:  # every leg's record signed
                signed = client.get(f"/api/trials/{leg['trial']}").json()["signature"]
                assert signed["statement"]["data_digest"] == leg["data_digest"]

            # a leg rerun by its two commits is the same leg, bit for bit
            first = played["legs"][0]["trial"]
            rerun = client.post(f"/api/trials/{first}/rerun")
            assert rerun.status_code == 201, rerun.text
            deadline = time.monotonic() + WAIT
            while (again := client.get(rerun.headers["location"]).json())["status"] != "finished":
                assert time.monotonic() < deadline, again
                time.sleep(0.5)
            assert again["reproduced"] is True, again
            assert again["away"]["commit"] == played["b"]["commit"], again
            assert again["data_digest"] == played["legs"][0]["data_digest"]

            ladder = client.get("/api/ladders/soccer-1v1").json()
            rows = {(r["repository"], r["matches"]): r for r in ladder["rows"]}
            top, bottom = ladder["rows"][0], ladder["rows"][-1]
            assert top["repository"] in (chaser, rival) and bottom["repository"] == still
            assert rows[(still, 1)]["losses"] == 2
            assert top["interval"][0] <= top["rating"] <= top["interval"][1]
            assert rows[(chaser, 2)]["rating"] > rows[(still, 1)]["rating"]
            assert client.get("/api/ladders/icreate-maze").status_code == 404
