"""The one check of a worker's filing: every claim its record does not bear out is named,
nothing is filed or signed then, and a worker whose filing is refused files an error."""

from __future__ import annotations

import datetime as dt

import pytest

from repository.digests import manifest_digest
from repository.index import Index
from repository.manifest import Code, Controller, Manifest, TaskVersion, Team, Versions
from repository.signing import Keyring
from repository.trial import Filing, Order, Trial
from scheduler.errors import FilingRefused
from scheduler.filing import Claims, Expected, filing_problems, record_differences
from scheduler.host import RecordFacts
from scheduler.queue import Queue
from scheduler.worker import Worker, WorkerConfig
from tests.helpers.manifests import trial_manifest

TOPICS = ["/clock", "/cmd_vel", "/lab/episode", "/odom"]
EXPECTED = Expected(values={"time_limit": 30.0}, version="1", digest_topics=TOPICS)
MANIFEST = trial_manifest(
    "icreate-maze",
    "1",
    {"time_limit": 30.0},
    4,
    model_sha256="0" * 64,
    repository="/r",
    commit="c" * 40,
).to_json()
OUTCOME = {"status": "finished", "outcome": "fail", "reason": "ran out", "metrics": {"reward": 2.5}}
RECORD = RecordFacts(
    MANIFEST,
    "d" * 64,
    OUTCOME,
    {"outcome.json": "sha256:" + "1" * 64, "controller.stdout.log": "sha256:" + "2" * 64},
)


def trial(rerun_of: int | None = None, **fields: object) -> Trial:
    now = dt.datetime.now(dt.UTC)
    values: dict[str, object] = {
        "id": 7, "repository": "/r", "ref": None, "commit": "c" * 40, "task": "icreate-maze",
        "params": {}, "seed": 4, "submitter": "alice", "public": True, "rerun_of": rerun_of,
        "status": "running", "outcome": None, "reason": "running", "created": now,
        "started": now, "finished": None, "worker": "w", "attempts": 1,
        "cancel_requested": False, "manifest": None, "manifest_digest": None,
        "data_digest": None, "digest_topics": None, "metrics": None, "backend": None,
        "wall_seconds": None, "mcap": None, "mcap_size": None, "stdout": None,
        "stderr": None, "reproduced": None, "divergence": None, **fields,
    }  # fmt: skip
    return Trial.model_validate(values)


def honest(**changes: object) -> Filing:
    fields: dict[str, object] = {
        "status": "finished", "outcome": "fail", "reason": "ran out", "manifest": MANIFEST,
        "manifest_digest": manifest_digest(MANIFEST), "data_digest": "d" * 64,
        "digest_topics": TOPICS, "metrics": {"reward": 2.5}, "mcap": "sha256:" + "9" * 64,
        "mcap_size": 1000, "stdout": "sha256:" + "2" * 64, **changes,
    }  # fmt: skip
    return Filing.model_validate(fields)


def problems(filing: Filing, record: RecordFacts | None = RECORD, **kwargs: object) -> list[str]:
    return filing_problems(trial(), filing, record, expected=EXPECTED, size=1000, **kwargs)  # type: ignore[arg-type]


def test_an_honest_filing_has_no_problem():
    """A filing that says what its record holds is signed as it is."""
    assert problems(honest()) == []


LIES = {
    "another data digest": ({"data_digest": "e" * 64}, "data_digest: the record's data digest is"),
    "a reward of 1e9": ({"metrics": {"reward": 1e9}}, "metrics: the record's differ in reward"),
    "another outcome": ({"outcome": "success"}, "outcome: the record says 'fail', not 'success'"),
    "another reason": ({"reason": "great"}, "reason: the record says 'ran out'"),
    "fewer digest topics": ({"digest_topics": ["/clock"]}, "digest_topics: the task's are"),
    "another size": ({"mcap_size": 1}, "mcap_size: the record is 1,000 bytes, not 1"),
    "another log": ({"stdout": "sha256:" + "3" * 64}, "stdout: the record's controller.stdout"),
    "another manifest digest": ({"manifest_digest": "f" * 64}, "manifest_digest: it is not"),
    "another trial's manifest": (
        {"manifest": {**MANIFEST, "seed": 5}},
        "manifest: its seed is 5, trial 7's is 4",
    ),
    "a verdict on no rerun": ({"reproduced": True}, "reproduced: trial 7 reruns no trial"),
}


@pytest.mark.parametrize("lie", sorted(LIES))
def test_each_claim_the_record_does_not_bear_out_is_named(lie):
    """Each claim that differs from the record or the trial is a problem naming it."""
    change, said = LIES[lie]
    found = problems(honest(**change))
    assert any(said in p for p in found), found


def test_a_record_of_another_trial_is_not_this_trials():
    """A record whose manifest is another trial's (its seed) is refused, however
    consistent the filing is with it."""
    other = {**MANIFEST, "seed": 5}
    record = RecordFacts(other, "d" * 64, OUTCOME, RECORD.attachments)
    found = problems(honest(manifest=other, manifest_digest=manifest_digest(other)), record)
    assert found == ["manifest: its seed is 5, trial 7's is 4"]


def test_a_rerun_s_verdict_is_the_lab_s():
    """A rerun reproduced exactly when its record's data digest is the original's."""
    original = trial(id=3, status="finished", outcome="fail", data_digest="d" * 64)
    rerun = trial(rerun_of=3)
    check = {"expected": EXPECTED, "size": 1000, "original": original}
    assert filing_problems(rerun, honest(reproduced=True), RECORD, **check) == []  # type: ignore[arg-type]
    lied = filing_problems(rerun, honest(reproduced=False), RECORD, **check)  # type: ignore[arg-type]
    assert lied == ["reproduced: the record's data digest is trial 3's, so it is True"]


@pytest.mark.parametrize(
    ("filing", "refused"),
    [
        (Filing(status="finished", outcome="success", reason="x"), "outcome: a filing without"),
        (
            Filing(status="finished", outcome="error", reason="x", metrics={"reward": 1e9}),
            "metrics: a filing without a record (mcap) claims none",
        ),
        (
            Filing(status="finished", outcome="error", reason="x", data_digest="d" * 64),
            "data_digest: a filing without a record (mcap) claims none",
        ),
        (Filing(status="finished", outcome="error", reason="x", stdout="sha256:" + "2" * 64), None),
        (Filing(status="cancelled", reason="cancelled while it ran"), None),
    ],
)
def test_a_filing_without_a_record_claims_nothing_to_check(filing, refused):
    """Without a record, only an error or a cancellation, with no digest or metrics
    (its logs say why it broke), is filed."""
    found = problems(filing, None)
    if refused is None:
        assert found == []
    else:
        assert any(refused in p for p in found), found


def test_a_demonstration_s_outcome_is_in_its_own_words():
    """A statement that claims no status (a demonstration's) is not held to a trial's
    outcome.json; one that does is, and a record without one is named."""
    demo = RecordFacts(MANIFEST, "d" * 64, {"achieved": True, "reason": "r"}, {})
    assert record_differences(Claims(manifest_digest(MANIFEST), "d" * 64), demo) == []
    claims = Claims(manifest_digest(MANIFEST), "d" * 64, status="finished", outcome="success")
    assert record_differences(claims, demo) == [
        "outcome: the record holds no outcome.json saying how it ended"
    ]


@pytest.fixture
def index(tmp_path):
    index = Index.open(f"sqlite:///{tmp_path / 'index.sqlite'}")
    index.add_user("alice", max_running=5)
    yield index
    index.close()


def claimed(queue: Queue) -> int:
    alice = queue.index.user("alice")
    queue.submit(
        alice, Order(repository="/r", commit="c" * 40, task="icreate-maze", seed=4, public=True)
    )
    claim = queue.claim("w")
    assert claim is not None
    return claim.id


def test_a_refused_filing_stores_and_signs_nothing(index, tmp_path):
    """The queue holds a filing to its check before storing it: refused, the trial is
    still running, unsigned; the check is not asked of a worker that lost the trial."""
    asked = []

    def refuse(trial: Trial, filing: Filing, original: Trial | None) -> None:
        asked.append(trial.id)
        raise FilingRefused(trial.id, ["data_digest: the record's data digest is x, not y"])

    queue = Queue(index, keyring=Keyring(tmp_path / "keys"), check=refuse)
    trial_id = claimed(queue)
    with pytest.raises(FilingRefused, match="was not filed"):
        queue.finish(trial_id, "w", honest())
    row = index.trial(trial_id)
    assert (row.status.value, row.signature, row.data_digest) == ("running", None, None)
    assert not queue.finish(trial_id, "another worker", honest())
    assert asked == [trial_id]


def test_a_worker_whose_filing_is_refused_files_an_error_saying_why(index, tmp_path):
    """A worker's refused filing is filed again as an error naming what the lab found,
    without the record, and that is what the lab signs."""

    def refuse_records(trial: Trial, filing: Filing, original: Trial | None) -> None:
        if filing.mcap is not None:
            raise FilingRefused(trial.id, ["outcome: the record says 'fail', not 'success'"])

    queue = Queue(index, keyring=Keyring(tmp_path / "keys"), check=refuse_records)
    trial_id = claimed(queue)
    config = WorkerConfig(name="w", work=tmp_path / "work", cache=tmp_path / "cache")
    worker = Worker(queue, store=None, backend=None, host=None, config=config)  # type: ignore[arg-type]
    filed, filing = worker._finish(trial_id, honest(outcome="success"))
    assert filed and filing.mcap is None
    row = index.trial(trial_id)
    assert (row.status.value, row.outcome.value) == ("finished", "error")
    assert row.reason == (
        "the lab refused the worker's record of the trial: outcome: the record says 'fail',"
        " not 'success'"
    )
    assert row.signature is not None and row.signature["statement"]["mcap"] is None


def test_a_leg_s_record_names_both_of_its_teams_and_home_s_logs():
    """A match leg's manifest must name the trial's own code at home and its away team
    at away, and its stdout is home's log: the record of another pairing, or with the
    sides swapped, is refused."""
    home = Code("/home-team", "a" * 40, "sha256:" + "0" * 64, None, "", dirty=False)
    away = Code("/away-team", "b" * 40, "sha256:" + "0" * 64, None, "", dirty=False)
    team = Controller(("python", "c.py"), False, None, None)

    def leg_manifest(first: Code, second: Code) -> dict[str, object]:
        return Manifest.match(
            teams={"home": Team(first, team), "away": Team(second, team)},
            task=TaskVersion("soccer-1v1", "1"),
            parameters={"time_limit": 30.0},
            seed=4,
            runtime="in-process",
            versions=Versions.here(),
            model_sha256="0" * 64,
        ).to_json()

    leg = trial(
        kind="match",
        repository="/home-team",
        commit="a" * 40,
        task="soccer-1v1",
        away_repository="/away-team",
        away_commit="b" * 40,
    )
    expected = Expected(
        values={"time_limit": 30.0}, version="1", digest_topics=TOPICS, sides=("home", "away")
    )
    logs = {"outcome.json": "sha256:" + "1" * 64, "home.stdout.log": "sha256:" + "2" * 64}
    for manifest, wrong in (
        (leg_manifest(home, away), []),
        (leg_manifest(away, home), ["repository", "commit", "away repository", "away commit"]),
    ):
        filing = honest(manifest=manifest, manifest_digest=manifest_digest(manifest))
        record = RecordFacts(manifest, "d" * 64, OUTCOME, logs)
        found = filing_problems(leg, filing, record, expected=expected, size=1000)
        named = {p.split(" is ")[0] for p in found}
        assert named == {f"manifest: its {name}" for name in wrong}, found
    plain = filing_problems(
        leg,
        honest(manifest=leg_manifest(home, away)),
        RecordFacts(leg_manifest(home, away), "d" * 64, OUTCOME, RECORD.attachments),
        expected=expected,
        size=1000,
    )
    assert any(p.startswith("stdout: the record's home.stdout.log") for p in plain), plain
