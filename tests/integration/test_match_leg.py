"""A leg of a match, played in bubblewrap sandboxes (``scheduler.leg.run_leg``): the
example ball chaser against a team that connects and never steps wins by forfeit at
the deadline, the leg does not stall, and its record replays; two chasers play a
leg on the shared tick, both sides' commands in the record, which replays, and a
rerun of the same two teams gives the same bytes."""

from __future__ import annotations

import asyncio
import json
import shutil
from pathlib import Path

import pytest

from labd.recorder.reader import read_messages
from labd.replay import replay_filed
from labd.trial import LabHost
from repository.trial import Order, Outcome
from scheduler.leg import LegOptions, run_leg
from scheduler.runner import RunOptions
from tests.helpers.sandboxes import make_backend

pytestmark = [pytest.mark.integration, pytest.mark.timeout(400)]
ROOT = Path(__file__).resolve().parents[2]
CHASER = ROOT / "controllers" / "examples" / "soccer-chaser"
STILL = """\
import time
from controllers.client import Lab

with Lab.connect() as lab:  # connected, and never a step
    lab.subscribe("/player_0/observation/ball_ego_position", "std_msgs/msg/Float64MultiArray")
    time.sleep(600)
"""


def still_team(folder: Path) -> Path:
    folder.mkdir()
    (folder / "lab.toml").write_text('[controller]\ncommand = ["python", "still.py"]\n')
    (folder / "still.py").write_text(STILL)
    return folder


def play(cache: Path, out: Path, home: Path, away: Path, seed: int, **options: float):
    backend = make_backend("bwrap", cache)
    orders = {
        side: Order(repository=str(team), task="soccer-1v1", seed=seed)
        for side, team in (("home", home), ("away", away))
    }
    run = RunOptions(first_step=float(options.pop("first_step", 60.0)))
    return asyncio.run(
        run_leg(
            orders,
            backend=backend,
            host=LabHost(),
            out=out,
            cache=cache,
            options=LegOptions(run=run, **options),
        )
    )


def test_a_team_that_never_steps_forfeits_at_the_deadline(cache, tmp_path):
    still = still_team(tmp_path / "still")
    # the first step's deadline, long enough for the chaser beside a busy lab (it steps
    # within a second or two on an idle machine), short enough for the test
    leg = play(cache, tmp_path / "leg", CHASER, still, seed=2, first_step=15.0)
    assert leg.outcome is Outcome.SUCCESS, leg.reason
    assert leg.metrics["winner"] == "home" and leg.metrics["ended_by"] == "forfeit"
    assert leg.metrics["forfeited"] == "away"
    assert "away sent no /lab/step within 15 s of its start" in leg.reason, leg.reason
    assert leg.metrics["ticks"] == 0  # the deadline ended it at tick 0, not a sandbox limit
    assert leg.mcap is not None
    manifest = json.loads((tmp_path / "leg" / "manifest.json").read_text())
    assert manifest["kind"] == "match" and sorted(manifest["teams"]) == ["away", "home"]
    assert manifest["teams"]["away"]["controller"]["command"] == ["python", "still.py"]
    verdict = json.loads(replay_filed(leg.mcap, tmp_path / "replay").verdict)
    assert verdict["verified"] is True, verdict


def test_two_chasers_play_on_the_shared_tick_and_a_rerun_is_identical(cache, tmp_path):
    first = play(cache, tmp_path / "one", CHASER, CHASER, seed=2, step_deadline=10.0)
    assert first.outcome is Outcome.SUCCESS, first.reason
    assert first.metrics["ended_by"] in {"goal", "time"}, first.metrics
    assert first.metrics["ticks"] > 10
    topics = [m.topic for m in read_messages(first.mcap)]
    assert {"/home/player_0/action", "/away/player_0/action"} <= set(topics)
    # each tick's commands are home's, then away's, before the tick's observations
    actions = [t for t in topics if t.endswith("/action")]
    assert actions[:4] == ["/home/player_0/action", "/away/player_0/action"] * 2
    verdict = json.loads(replay_filed(first.mcap, tmp_path / "replay").verdict)
    assert verdict["verified"] is True, verdict
    again = play(cache, tmp_path / "two", CHASER, CHASER, seed=2, step_deadline=10.0)
    assert again.data_digest == first.data_digest
    assert again.manifest_digest == first.manifest_digest
    assert again.metrics == first.metrics


def test_the_house_still_team_steps_to_the_end_and_the_chaser_scores_as_alone(cache, tmp_path):
    """The house's still team (controllers/examples/soccer-still) never forfeits: the
    chaser scores against it on the very tick it scores alone (seed 2: tick 399), since
    a still side is what a lone trial's away side is."""
    still = ROOT / "controllers" / "examples" / "soccer-still"
    leg = play(cache, tmp_path / "leg", CHASER, still, seed=2)
    assert leg.outcome is Outcome.SUCCESS, leg.reason
    assert (leg.metrics["winner"], leg.metrics["ended_by"]) == ("home", "goal")
    assert (leg.metrics["home_goals"], leg.metrics["away_goals"], leg.metrics["ticks"]) == (
        1, 0, 399
    )  # fmt: skip
    assert (tmp_path / "leg" / "away.stdout.log").read_text().startswith("episode over: tick 399")


@pytest.mark.skipif(shutil.which("node") is None, reason="Node.js is not installed")
def test_a_javascript_team_plays_a_python_one(cache, tmp_path):
    """The JavaScript ball chaser (controllers/examples/soccer-chaser-js, on roslibjs) at
    home against the Python still team: it scores on seed 2 as it does alone (tick 399)."""
    chaser_js = ROOT / "controllers" / "examples" / "soccer-chaser-js"
    still = ROOT / "controllers" / "examples" / "soccer-still"
    leg = play(cache, tmp_path / "leg", chaser_js, still, seed=2)
    assert leg.outcome is Outcome.SUCCESS, leg.reason
    assert (leg.metrics["winner"], leg.metrics["ended_by"], leg.metrics["ticks"]) == (
        "home", "goal", 399
    )  # fmt: skip


def test_a_leg_that_cannot_be_played_is_an_error_naming_the_team(cache, tmp_path):
    """A team without lab.toml leaves the leg unplayed (no record, no result); a task
    nobody has is an error too, not an exception."""
    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "c.py").write_text("pass\n")
    leg = play(cache, tmp_path / "leg", CHASER, broken, seed=0)
    assert leg.outcome is Outcome.ERROR and leg.mcap is None
    assert leg.reason.startswith("the leg was not played: away could not start: "), leg.reason
    assert "lab.toml" in leg.reason and leg.metrics == {}
    backend = make_backend("bwrap", cache)
    orders = {
        side: Order(repository=str(CHASER), task="no-such-task", seed=0)
        for side in ("home", "away")
    }
    unknown = asyncio.run(
        run_leg(orders, backend=backend, host=LabHost(), out=tmp_path / "x", cache=cache)
    )
    assert unknown.outcome is Outcome.ERROR and "no-such-task" in unknown.reason
