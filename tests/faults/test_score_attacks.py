"""Attacks on a score, as a submitter who wants a better number would make them.

Each was found to work on an earlier lab (issue: scores nobody can game) and must not:

- the held-out seed reached the controller (``LAB_SEED``, ``/lab/episode``) and went back
  to its submitter through each episode's public wall time and through its log, served
  by digest to anyone (``GET /api/blobs/{digest}``);
- cancelling the episodes it would fail, one by one, made an evaluation 100 % and first;
- rerunning an evaluation until it came out lucky put the luckiest run on the board;
- a remote worker's replay verdict was taken as the lab's "verified";
- a held-out suite could be probed by evaluating it again and again.
"""

# ruff: noqa: F811 (the API's fixtures, imported from test_api, are the tests' arguments)
from __future__ import annotations

import asyncio
import json

import pytest

from labd.replay import replay
from labd.workers import LOCAL_WORKERS
from repository.index import Derived
from repository.trial import Filing, Order
from repository.well_known import LOGS, REPLAY
from scheduler.remote import PROTOCOL, PROTOCOL_HEADER
from scheduler.runner import run_trial
from tests.fakes import verify_episodes
from tests.helpers.githttp import GitRepo
from tests.labd.test_api import api, auth, repo, service, token  # noqa: F401 (fixtures)
from tests.labd.test_api_evaluations import evaluate

SEED = 6_150_431_977_200_413_321  # a held-out-like seed: 63 bits
# Prints every seed it can find, then steps until the episode ends (its time limit).
SPY = """\
import json, os, sys
from controllers.client import EpisodeOver, Lab

told = os.environ.get("LAB_SEED")
with Lab.connect() as lab:
    episode = lab.subscribe("/lab/episode", "lab_msgs/msg/Episode")
    lab.step()
    seen = episode.get()["seed"]
    print(json.dumps({"env": told, "topic": seen, "environ": sorted(os.environ)}), flush=True)
"""
SPY_TOML = '[controller]\ncommand = ["python", "spy.py"]\ntask = "icreate-maze"\n'


def _run(backend, cache, host, tmp_path, order: Order, *, blind: bool = False):
    out = tmp_path / f"run-{len(list(tmp_path.glob('run-*')))}"
    return asyncio.run(
        run_trial(order, blind=blind, backend=backend, host=host, out=out, cache=cache)
    )


@pytest.mark.integration
def test_a_held_out_episode_runs_blind_and_its_record_still_replays(backend, cache, host, tmp_path):
    """Its controller finds its seed neither in its environment nor on /lab/episode (nor
    any episode number); the manifest says it ran blind, and the lab's replay of the
    record verifies. The same controller on the same seed, not blind, sees it."""
    spy = GitRepo.create(tmp_path / "spy", {"lab.toml": SPY_TOML, "spy.py": SPY}).path
    blind = _run(backend, cache, host, tmp_path, Order(repository=str(spy), seed=SEED), blind=True)
    told = json.loads((blind.folder / LOGS["stdout"]).read_text().splitlines()[-1])
    assert (told["env"], told["topic"]) == (None, 0)
    assert not [name for name in told["environ"] if "SEED" in name or "EPISODE" in name]
    assert blind.manifest.blind is True and blind.manifest.seed == SEED
    assert str(SEED) not in (blind.folder / LOGS["stdout"]).read_text()
    assert replay(blind.mcap).verified

    seen = _run(backend, cache, host, tmp_path, Order(repository=str(spy), seed=SEED))
    told = json.loads((seen.folder / LOGS["stdout"]).read_text().splitlines()[-1])
    assert (told["env"], told["topic"]) == (str(SEED), SEED)
    assert "blind" not in seen.manifest.to_json()  # a trial's manifest is as it always was


def _claim_and_file(service, worker: str, outcomes: dict[int, str], stdout: bytes = b"") -> None:
    """Claim queued trials as ``worker`` and file those in ``outcomes`` (others go back)."""
    service.queue.check = None
    log = service.store.put_bytes(stdout) if stdout else None
    record = service.store.put_bytes(b"a record, as far as this test goes")
    left = dict(outcomes)
    while left:
        claim = service.queue.claim(worker)
        assert claim is not None, f"trials {sorted(left)} were never claimed"
        if claim.id not in left:
            service.queue.release_worker(worker)
            continue
        outcome = left.pop(claim.id)
        filing = Filing(
            status="finished",
            outcome=outcome,
            reason=f"{outcome} at tick 9",
            data_digest=f"{claim.id:064x}",
            metrics={"reward": 1.0 if outcome == "success" else 0.0},
            wall_seconds=5.0 * (claim.order.seed % 4),  # the timing channel: seed % 4 x 5 s
            stdout=log,
            mcap=record,
            mcap_size=34,
        )
        assert service.queue.finish(claim.id, worker, filing)


async def test_a_held_out_evaluation_tells_its_submitter_the_aggregate_alone(
    api, service, token, repo
):
    """Its claims are blind; while it runs, nobody sees its episodes, their timings or
    their positions in the queue; no episode can be cancelled alone; its episodes' logs
    are served to nobody, by digest or otherwise; when it has ended its submitter sees
    the rate, its interval, the mean reward and whether it verified: nothing per episode."""
    made = await evaluate(api, token, repo, suite="test")
    assert made.status_code == 201, made.text
    evaluation = made.json()
    whole = service.evaluations.get(evaluation["id"], reveal=True)
    ids = [r.trial for r in whole.rows]
    claim = service.queue.claim("w")
    assert claim is not None and claim.id == ids[0] and claim.blind
    status = (await api.get("/api/status")).json()
    assert status["running"] == [] and status["queued"] == 0  # its 50 episodes are not shown
    cancel = await api.post(f"/api/trials/{ids[1]}/cancel", headers=auth(token))
    assert cancel.status_code == 409 and f"evaluation {evaluation['id']}" in cancel.json()["error"]
    service.queue.release_worker("w")
    early = await api.get(f"/api/evaluations/compare?a={evaluation['id']}&b={evaluation['id']}")
    assert early.status_code == 422 and "once it has ended" in early.json()["error"]
    _claim_and_file(
        service, "w", {t: "success" if n % 2 else "fail" for n, t in enumerate(ids)}, b"seed 3\n"
    )
    log = service.index.trial(ids[0]).stdout
    assert log is not None
    for headers in ({}, auth(token)):
        guessed = await api.get(f"/api/blobs/{log}", headers=headers)
        assert guessed.status_code == 404, guessed.text
    done = (await api.get(f"/api/evaluations/{evaluation['id']}")).json()
    assert done["status"] == "finished" and done["hidden"]
    assert (done["success_rate"], done["successes"], done["episodes"]) == (0.5, 25, 50)
    assert done["success_interval"] is not None and done["mean_reward"] == 0.5
    assert done["rows"] == [] and done["compute_seconds"] is None
    assert "wall" not in json.dumps(done)  # no episode's wall time, in any field
    said = done["signature"]["statement"]
    assert "rows" not in said and said["episodes_sha256"]
    listed = (await api.get("/api/evaluations", params={"suite": "test"})).json()
    assert listed["evaluations"][0]["rows"] == []
    compared = (
        await api.get(f"/api/evaluations/compare?a={evaluation['id']}&b={evaluation['id']}")
    ).json()  # counts of its whole rows, never which episodes
    assert (compared["paired"], compared["pairs"]["both"]) == (50, 25)


async def test_cancelling_the_episodes_it_would_fail_buys_nothing(api, service, token, repo):
    """The attack: 2 episodes of 20 succeed, the other 18 are cancelled one by one.
    Each cancel is refused; cancelling the evaluation makes it partial, scored 2 of 20,
    signed as partial, and off the leaderboard."""
    evaluation = (await evaluate(api, token, repo)).json()
    ids = [r["trial"] for r in evaluation["rows"]]
    _claim_and_file(service, "w", {ids[0]: "success", ids[1]: "success"})
    for trial_id in ids[2:]:
        refused = await api.post(f"/api/trials/{trial_id}/cancel", headers=auth(token))
        assert refused.status_code == 409, refused.text
    assert service.index.trial(ids[2]).status.value == "queued"
    cancelled = await api.post(f"/api/evaluations/{evaluation['id']}/cancel", headers=auth(token))
    shown = cancelled.json()
    assert (shown["status"], shown["partial"], shown["success_rate"]) == ("cancelled", True, 0.1)
    assert shown["signature"]["statement"]["partial"] is True
    verify_episodes(service, ids[:2])
    board = (await api.get("/api/tasks/icreate-maze/leaderboard?suite=dev")).json()
    assert board["rows"] == []


async def test_rerunning_until_lucky_changes_no_row(api, service, token, repo):
    """A commit's row is its first evaluation: a luckier rerun (by anyone) and a luckier
    second evaluation never replace it; a rerun that diverged marks it not reproducible,
    and the row keeps its submitter."""
    first = (await evaluate(api, token, repo)).json()
    ids = [r["trial"] for r in first["rows"]]
    _claim_and_file(service, "w", {t: "success" if n < 5 else "fail" for n, t in enumerate(ids)})
    verify_episodes(service, ids)
    mallory = service.index.add_user("mallory", max_daily=500)
    rerun = await api.post(f"/api/evaluations/{first['id']}/rerun", headers=auth(mallory))
    assert rerun.status_code == 201, rerun.text
    again = rerun.json()
    assert again["submitter"] == "mallory" and again["rerun_of"] == first["id"]
    lucky = [r["trial"] for r in again["rows"]]
    _claim_and_file(service, "w", dict.fromkeys(lucky, "success"))
    verify_episodes(service, lucky)
    second = (await evaluate(api, token, repo)).json()
    more = [r["trial"] for r in second["rows"]]
    _claim_and_file(service, "w", dict.fromkeys(more, "success"))
    verify_episodes(service, more)
    board = (await api.get("/api/tasks/icreate-maze/leaderboard?suite=dev")).json()
    [row] = board["rows"]
    assert (row["evaluation"], row["submitter"], row["success_rate"]) == (
        first["id"],
        "alice",
        0.25,
    )
    assert row["reproducible"] is False and f"rerun {again['id']} diverged" in row["note"]


async def test_a_remote_workers_replay_verdict_is_not_the_labs(api, service, repo, token):
    """A worker elsewhere is told not to replay, and a verdict it files anyway is
    refused: the lab replays what it filed itself. The lab's own worker processes'
    verdicts are taken."""
    remote = service.index.add_user("site-b", worker=True)
    own = service.index.add_user(LOCAL_WORKERS, worker=True)
    headers = {PROTOCOL_HEADER: str(PROTOCOL)}
    hello = await api.get("/api/workers/hello", headers={**headers, **auth(remote)})
    assert hello.json()["replays"] is False
    hello = await api.get("/api/workers/hello", headers={**headers, **auth(own)})
    assert hello.json()["replays"] is True

    evaluation = (await evaluate(api, token, repo)).json()
    ids = [r["trial"] for r in evaluation["rows"]]
    _claim_and_file(service, "site-b@box", {ids[0]: "success"})
    # the record the filing named: the verdict's blob is uploaded first, as a worker does
    verdict = json.dumps({"verified": True}).encode()
    digest = service.store.put_bytes(verdict)
    item = {
        "name": REPLAY,
        "digest": digest,
        "size": len(verdict),
        "media_type": "application/json",
    }
    posted = await api.post(
        f"/api/workers/trials/{ids[0]}/derived",
        json={"worker": "box", "item": item},
        headers={**headers, **auth(remote)},
    )
    assert posted.status_code == 422 and "the lab's own word" in posted.json()["error"]
    assert REPLAY not in service.index.derived(ids[0])
    shown = (await api.get(f"/api/evaluations/{evaluation['id']}")).json()
    assert shown["rows"][0]["verified"] is None
    # what the lab's replays take up: this trial; not one its own workers filed
    assert service.index.unreplayed(service.replays.trusted) == ids[0]
    service.index.put_derived(ids[0], Derived(REPLAY, digest, len(verdict), "application/json"))
    _claim_and_file(service, f"{LOCAL_WORKERS}@p1", {ids[1]: "success"})
    assert service.index.unreplayed(service.replays.trusted) is None


async def test_a_held_out_suite_is_scored_not_probed(api, service, repo):
    """One held-out evaluation per commit and suite version for each user (a rerun
    counts), five a day: the next is refused with the budget it is over, and nothing
    is queued. Another user's rerun is theirs to spend."""
    token = service.index.add_user("carol", max_daily=1000)
    first = await evaluate(api, token, repo, suite="test")
    assert first.status_code == 201, first.text
    again = await evaluate(api, token, repo, suite="test")
    assert again.status_code == 429 and "held-out evaluation" in again.json()["error"]
    mine = await api.post(f"/api/evaluations/{first.json()['id']}/rerun", headers=auth(token))
    assert mine.status_code == 429
    queued = service.queue.queued()
    other = service.index.add_user("bob", max_daily=1000)
    theirs = await api.post(f"/api/evaluations/{first.json()['id']}/rerun", headers=auth(other))
    assert theirs.status_code == 201, theirs.text
    assert service.queue.queued() == queued + 50
    tags = GitRepo(repo)
    for n in range(4):  # bob's rerun, then four commits: his five of the day
        tags.commit({"c.py": f"print({n})\n"}, f"commit {n}")
        reply = await evaluate(api, other, repo, suite="test")
        assert reply.status_code == 201, reply.text
    tags.commit({"c.py": "print('over')\n"}, "over")
    queued = service.queue.queued()
    over = await evaluate(api, other, repo, suite="test")
    assert over.status_code == 429 and "in the last 24 hours" in over.json()["error"]
    assert service.queue.queued() == queued
    dev = await evaluate(api, other, repo)  # the public suite has no such budget
    assert dev.status_code == 201, dev.text
