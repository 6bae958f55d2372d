"""The soccer pack (``labd.sim.soccer``): dm_control's soccer unchanged behind the lab's
topics. Its catalog of observations is dm_control's own; the same seed and actions give
dm_control's observations bit for bit; commands are checked and clipped; a leg ends at
a goal or its time limit, judged from home's view."""

from __future__ import annotations

import math

import numpy as np
import pytest
from dm_control.locomotion import soccer

from labd.errors import MessageError
from labd.sim.simulation import Simulation
from labd.sim.soccer.task import observation_keys
from repository.trial import EpisodeStatus


def dm_controls_own(team_size: int, seed: int, time_limit: float = 45.0):
    return soccer.load(
        team_size=team_size,
        time_limit=time_limit,
        random_state=seed,
        disable_walker_contacts=False,
        enable_field_box=True,
        terminate_on_goal=True,
        walker_type=soccer.WalkerType.BOXHEAD,
    )


@pytest.mark.parametrize("team_size", [1, 2])
def test_the_catalog_is_dm_controls_observation(team_size):
    """Every player observes the keys the pack lists, with their shapes; a home player in
    the pack's order (an away player's lists its opponents, home's players, first)."""
    env = dm_controls_own(team_size, seed=0)
    timestep = env.reset()
    expected = observation_keys(team_size)
    for k, observation in enumerate(timestep.observation):
        found = [(key, np.asarray(value).shape[1:]) for key, value in observation.items()]
        if k < team_size:
            assert found == expected
        else:
            assert sorted(found) == sorted(expected)


def test_the_same_seed_and_actions_give_dm_controls_observations_bit_for_bit():
    """Driven by the same actions, the lab's leg and dm_control's environment for the
    same seed observe the same bytes, player by player."""
    sim = Simulation("soccer-2v2", {}, seed=5)
    env = dm_controls_own(2, seed=5)
    env.reset()
    rng = np.random.default_rng(5)
    topics = {
        (side, i): f"/{side}/player_{i}/action" for side in ("home", "away") for i in range(2)
    }
    for _ in range(60):
        actions = rng.uniform(-1, 1, (4, 3))
        for k, topic in enumerate(topics.values()):
            sim.task.command(topic, {"data": actions[k].tolist()})
        sim.step()
        timestep = env.step(list(actions))
        for k, (side, i) in enumerate(topics):
            ours = sim.task.observe(
                sim.physics, f"/{side}/player_{i}/observation/ball_ego_position", {}
            )
            assert ours is not None
            theirs = np.asarray(timestep.observation[k]["ball_ego_position"])[0]
            assert np.array_equal(np.asarray(ours["data"]), theirs)
            joints = sim.task.observe(sim.physics, f"/{side}/player_{i}/observation/joints_pos", {})
            assert joints is not None
            assert np.array_equal(
                joints["data"], np.asarray(timestep.observation[k]["joints_pos"])[0]
            )


def test_commands_are_checked_clipped_and_held():
    sim = Simulation("soccer-1v1", {}, seed=1)
    task = sim.task
    with pytest.raises(MessageError, match="must hold 3 values"):
        task.command("/home/player_0/action", {"data": [1.0, 0.0]})
    with pytest.raises(MessageError, match="finite"):
        task.command("/home/player_0/action", {"data": [1.0, math.nan, 0.0]})
    with pytest.raises(MessageError, match="not a command topic"):
        task.command("/home/player_1/action", {"data": [0.0, 0.0, 0.0]})
    assert not task.action(sim.physics).any()  # still: nothing taken
    task.command("/away/player_0/action", {"data": [2.0, -0.5, -3.0]})
    assert task.action(sim.physics).tolist() == [0.0, 0.0, 0.0, 1.0, -0.5, -1.0]
    assert task.clipped == {"/away/player_0/action": 1}
    sim.step()
    assert task.action(sim.physics).tolist() == [0.0, 0.0, 0.0, 1.0, -0.5, -1.0]  # held


def test_a_leg_nobody_scores_in_fails_at_its_time_limit():
    sim = Simulation("soccer-1v1", {"time_limit": 0.5}, seed=3)
    while sim.running:
        sim.step()
    assert sim.status is EpisodeStatus.FAILED and sim.truncated
    assert sim.reason.startswith("no goal in 0.5") and sim.reason.endswith(": 0-0")
    metrics = sim.metrics()
    assert (metrics["success"], metrics["home_goals"], metrics["away_goals"]) == (False, 0, 0)
    score = sim.task.observe(sim.physics, "/away/score", {})
    assert score == {"layout": {"dim": [], "data_offset": 0}, "data": [0, 0]}


def test_a_goal_ends_the_leg_and_each_side_reads_its_own_score():
    """Pushed into a leg where home's player has just scored (the ball moved into the
    away goal by hand: the leg's own detection decides), the leg ends for home."""
    sim = Simulation("soccer-1v1", {}, seed=4)
    arena = sim.env.inner.task.arena
    ball = sim.env.inner.task.ball
    goal = arena.away_goal  # where home scores
    middle = (np.asarray(goal.lower) + np.asarray(goal.upper)) / 2
    ball.set_pose(sim.physics, position=middle)
    sim.step()
    assert sim.status is EpisodeStatus.SUCCEEDED, sim.reason
    assert sim.reason.startswith("home scored at 0.025 s: 1-0")
    assert sim.task.observe(sim.physics, "/home/score", {})["data"] == [1, 0]
    assert sim.task.observe(sim.physics, "/away/score", {})["data"] == [0, 1]
    assert sim.metrics()["reward"] == 1.0 and sim.reward == 1.0
