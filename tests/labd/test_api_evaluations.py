"""Evaluations through the HTTP API in process: a commit queued on every episode of a
suite, its score as episodes are filed, the signature when the last has ended, cancel,
compare, the leaderboard, and a held-out suite's seeds and records kept private.

No workers run here: episodes are claimed and filed the way a worker files them.
"""

# ruff: noqa: F811 (the API's fixtures, imported from test_api, are the tests' arguments)
from __future__ import annotations

import json

import pytest

from repository.signing import Signature, verify
from repository.trial import Filing
from tests.fakes import verify_episodes
from tests.labd.test_api import api, auth, repo, service, token  # noqa: F401 (fixtures)

DEV = 20  # the maze's dev suite


async def evaluate(api, token, repo, **body):
    return await api.post(
        "/api/evaluations",
        json={"repository": str(repo), "task": "icreate-maze", **body},
        headers=auth(token),
    )


def file_episodes(service, outcomes: dict[int, tuple[str, float]]) -> None:
    """Claim queued episodes and file each trial in ``outcomes`` with its outcome and
    reward, as a worker would (the queue's hooks run; the record is not held to a file)."""
    service.queue.check = None
    left = dict(outcomes)
    while left:
        claim = service.queue.claim("w")
        assert claim is not None, f"trials {sorted(left)} were never claimed"
        outcome, reward = left.pop(claim.id, ("fail", 0.0)) if claim.id in left else (None, None)
        if outcome is None:
            service.queue.release_worker("w")  # not one of ours: back to the queue
            continue
        filing = Filing(
            status="finished",
            outcome=outcome,
            reason=f"{outcome} at tick 9",
            data_digest=f"{claim.id:064x}",
            metrics={"reward": reward},
        )
        assert service.queue.finish(claim.id, "w", filing)


async def test_an_evaluation_queues_every_episode_and_is_scored_and_signed(
    api, service, token, repo
):
    """The dev suite's 20 seeds are queued as 20 trials; as they are filed the score
    follows with its intervals; the last one ends it, and the lab signs it."""
    reply = await evaluate(api, token, repo)
    assert reply.status_code == 201, reply.text
    evaluation = reply.json()
    assert reply.headers["location"].endswith(f"/api/evaluations/{evaluation['id']}")
    assert (evaluation["suite"], evaluation["suite_version"], evaluation["status"]) == (
        "dev",
        1,
        "queued",
    )
    assert [r["seed"] for r in evaluation["rows"]] == list(range(DEV))
    assert evaluation["episodes"] == DEV and evaluation["queued"] == DEV
    trials = [(await api.get(f"/api/trials/{r['trial']}")).json() for r in evaluation["rows"]]
    assert {t["commit"] for t in trials} == {evaluation["commit"]}
    assert [t["seed"] for t in trials] == list(range(DEV))

    ids = [r["trial"] for r in evaluation["rows"]]
    file_episodes(service, {t: ("success", 1.0) for t in ids[:14]})
    half = (await api.get(f"/api/evaluations/{evaluation['id']}")).json()
    assert half["status"] == "running" and half["signature"] is None
    assert (half["done"], half["successes"], half["success_rate"]) == (14, 14, None)
    file_episodes(service, {t: ("fail", 0.0) for t in ids[14:]})
    done = (await api.get(f"/api/evaluations/{evaluation['id']}")).json()
    score = done
    assert done["status"] == "finished" and not done["partial"]
    assert (score["done"], score["successes"], score["success_rate"]) == (DEV, 14, 0.7)
    low, high = score["success_interval"]
    assert 0.48 < low < 0.7 < high < 0.86  # Wilson, 14 of 20
    assert score["mean_reward"] == pytest.approx(0.7)
    assert not score["verified"]  # no episode was replayed here
    keys = (await api.get("/api/keys")).json()["keys"]
    signature = done["signature"]
    verify(Signature.from_json(signature), keys)
    said = signature["statement"]
    assert said["schema"] == "labd.evaluation/2" and said["commit"] == evaluation["commit"]
    assert [e["outcome"] for e in said["rows"]] == ["success"] * 14 + ["fail"] * 6
    assert [e["seed"] for e in said["rows"]] == list(range(DEV))
    assert (said["episodes"], said["successes"], said["partial"]) == (DEV, 14, False)


async def test_the_daily_limit_counts_episodes_and_a_refusal_leaves_nothing(api, service, repo):
    token = service.index.add_user("carol", max_daily=DEV - 1)
    reply = await evaluate(api, token, repo)
    assert reply.status_code == 429, reply.text
    assert "these 20 would take it past" in reply.json()["error"]
    assert (await api.get("/api/trials")).json()["trials"] == []
    assert (await api.get("/api/evaluations")).json()["evaluations"] == []


@pytest.mark.parametrize(
    ("body", "words"),
    [
        ({"suite": "nightly"}, "has no suite 'nightly'; its suites: dev, test"),
        ({"suite": "Dev!"}, "has no suite"),
        ({"task": "no-such-task"}, "no-such-task"),
        ({"ref": "no-such-branch"}, "no-such-branch"),
        ({"seed": 3}, "seed"),  # an evaluation's seeds are its suite's
    ],
)
async def test_bad_evaluations_are_refused_and_leave_nothing(api, token, repo, body, words):
    reply = await evaluate(api, token, repo, **body)
    assert reply.status_code in (404, 422), reply.text
    assert words in reply.json()["error"]
    assert (await api.get("/api/trials")).json()["trials"] == []


async def test_a_held_out_suite_keeps_its_seeds_and_records_until_it_is_retired(
    api, service, token, repo
):
    """The test suite's seeds come from the lab's secret: the API shows its aggregate
    alone, never an episode, its trials answer 403 and stay out of the lists, until the
    operator retires the suite version; a retired suite takes no new evaluation."""
    token = service.index.add_user("dave", max_daily=500)
    reply = await evaluate(api, token, repo, suite="test")
    assert reply.status_code == 201, reply.text
    evaluation = reply.json()
    assert evaluation["held_out"] and evaluation["episodes"] == 50 and evaluation["hidden"]
    assert evaluation["rows"] == [] and evaluation["queued"] is None
    trial = service.evaluations.get(evaluation["id"], reveal=True).rows[0].trial
    hidden = await api.get(f"/api/trials/{trial}")
    assert hidden.status_code == 403 and "held-out suite" in hidden.json()["error"]
    assert (await api.get(f"/api/trials/{trial}/data.mcap")).status_code == 403
    assert (await api.get("/api/trials")).json()["trials"] == []
    rerun = await api.post(f"/api/trials/{trial}/rerun", headers=auth(token))
    assert rerun.status_code == 403
    seeds = [r.seed for r in service.evaluations.get(evaluation["id"], reveal=True).rows]
    assert len(set(seeds)) == 50 and not set(seeds) & set(range(DEV))
    text = json.dumps((await api.get(f"/api/evaluations/{evaluation['id']}")).json())
    assert not any(str(s) in text for s in seeds)

    assert service.evaluations.retire("icreate-maze", "test", 1) == 50
    shown = (await api.get(f"/api/evaluations/{evaluation['id']}")).json()
    assert [r["seed"] for r in shown["rows"]] == seeds
    assert (await api.get(f"/api/trials/{trial}")).json()["seed"] == seeds[0]
    task = (await api.get("/api/tasks/icreate-maze")).json()
    assert {
        s["name"]: (s["held_out"], s["retired"], s["seeds"] is None) for s in task["suites"]
    } == {
        "dev": (False, False, False),
        "test": (True, True, True),
    }
    again = await evaluate(api, token, repo, suite="test")
    assert again.status_code == 422 and "was retired" in again.json()["error"]


async def test_cancel_keeps_what_finished_and_leaves_the_leaderboard(api, service, token, repo):
    """A cancelled evaluation keeps its finished episodes, is marked partial, counts
    its unfinished ones as no success, and is not ranked (nor is its commit, by a later
    evaluation); two finished ones are compared episode by episode and ranked once the
    lab has verified them."""
    token = service.index.add_user("erin", max_daily=500)
    a = (await evaluate(api, token, repo, ref="v1")).json()
    file_episodes(service, {r["trial"]: ("success", 1.0) for r in a["rows"][:3]})
    cancelled = await api.post(f"/api/evaluations/{a['id']}/cancel", headers=auth(token))
    assert cancelled.status_code == 200, cancelled.text
    c = cancelled.json()
    assert c["status"] == "cancelled" and c["partial"]
    assert c["partial_reason"] == "cancelled by its submitter (17 episodes unfinished)"
    assert (c["done"], c["successes"], c["success_rate"]) == (3, 3, 3 / DEV)
    said = c["signature"]["statement"]
    assert (said["status"], said["partial"], said["successes"]) == ("cancelled", True, 3)

    b = (await evaluate(api, token, repo)).json()
    d = (await evaluate(api, token, repo, ref="v1")).json()  # a's commit: a stays its row
    ids_b, ids_d = [r["trial"] for r in b["rows"]], [r["trial"] for r in d["rows"]]
    file_episodes(service, {t: ("success" if n < 18 else "fail", 1.0) for n, t in enumerate(ids_b)})
    file_episodes(service, {t: ("success" if n < 8 else "fail", 0.5) for n, t in enumerate(ids_d)})
    board = (await api.get("/api/tasks/icreate-maze/leaderboard?suite=dev")).json()
    assert [(r["evaluation"], r["rank"]) for r in board["rows"]] == [(b["id"], None)]
    assert board["rows"][0]["note"].startswith("not ranked: its episodes' replays")
    verify_episodes(service, ids_b)
    board = (await api.get("/api/tasks/icreate-maze/leaderboard?suite=dev")).json()
    assert [(r["evaluation"], r["rank"], r["tie"]) for r in board["rows"]] == [(b["id"], 1, False)]
    compared = (await api.get(f"/api/evaluations/compare?a={b['id']}&b={d['id']}")).json()
    assert compared["pairs"] == {"both": 8, "only_a": 10, "only_b": 0, "neither": 2}
    assert compared["p_value"] == pytest.approx(2 / 1024)
    assert "succeeds on 10 episodes where B" in compared["said"]
    test = (await evaluate(api, token, repo, suite="test")).json()
    across = await api.get(f"/api/evaluations/compare?a={b['id']}&b={test['id']}")
    assert across.status_code == 422 and "only evaluations of one suite" in across.json()["error"]
    listed = (await api.get("/api/evaluations", params={"suite": "dev"})).json()["evaluations"]
    assert [e["id"] for e in listed] == [d["id"], b["id"], a["id"]]
    other = service.index.add_user("frank")
    refused = await api.post(f"/api/evaluations/{b['id']}/cancel", headers=auth(other))
    assert refused.status_code == 403
