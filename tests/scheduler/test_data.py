"""The data a controller learns from: lab.toml's [data] pinned at submit time, checked and
mounted at run time; refused, with a reason, when it cannot be pinned or given as pinned."""

from __future__ import annotations

import pytest

from labd.graph.types import TypeRegistry
from labd.trial import LabHost
from repository.blobs import BlobStore
from repository.index import Index
from repository.trial import Kind, Order, Outcome, PinnedRecord, Status
from scheduler import controller
from scheduler.controller import DataQuery, DataSpec
from scheduler.data import DataPolicy, LocalArchive, materialize, resolve
from scheduler.errors import ControllerConfigError, DataUnavailable, InvalidData
from tests.labd.test_recorder import record

TASK = "icreate-maze"


@pytest.fixture
def archive(database_url, tmp_path):
    index = Index.open(database_url)
    yield LocalArchive(index, BlobStore(str(tmp_path / "blobs")))
    index.close()


def finished(
    archive: LocalArchive,
    *,
    kind: Kind = Kind.DEMONSTRATION,
    outcome: Outcome = Outcome.SUCCESS,
    user: str = "ann",
    public: bool = True,
    task: str = TASK,
    size: int = 1000,
    record: bool = True,
) -> int:
    index = archive.index
    order = Order(repository="robot:icreate-1", task=task, seed=3, public=public, kind=kind)
    trial = index.add_trial(order, submitter=user)
    index.update(
        trial,
        status=Status.FINISHED.value,
        outcome=outcome.value,
        data_digest=f"{trial:064x}" if record else None,
        digest_topics=["/odom", "/cmd_vel"] if record else None,
        mcap=f"sha256:{trial:064x}" if record else None,
        mcap_size=size if record else None,
    )
    return trial


def test_lab_toml_data_is_read_and_its_mistakes_named(tmp_path):
    """[data] takes trial ids and a query; a wrong key or value says what is expected."""
    base = '[controller]\ncommand = ["python", "c.py"]\n'
    (tmp_path / "lab.toml").write_text(
        base + '[data]\ntrials = [4, 2, 4]\nquery = { kind = "demonstration", limit = 3 }\n'
    )
    assert controller.load(tmp_path).data == DataSpec(
        (4, 2), DataQuery(kind=Kind.DEMONSTRATION, limit=3)
    )
    for text, message in (
        ("[data]\n", "names no trials and no query"),
        ('[data]\ntrials = ["12"]\n', "trials must be a list of trial ids"),
        ("[data]\nquery = { colour = 1 }\n", "query has no key 'colour'"),
        ('[data]\nquery = { kind = "demo" }\n', "query.kind is trial or demonstration"),
        ("[data]\nquery = { limit = 0 }\n", "query.limit must be a positive integer"),
        ("[data]\nfrom = 1\n", "[data] has no key 'from'"),
    ):
        (tmp_path / "lab.toml").write_text(base + text)
        with pytest.raises(ControllerConfigError, match=message.replace("[", r"\[")):
            controller.load(tmp_path)


def test_a_query_is_pinned_to_the_newest_matching_public_records(archive):
    """The query takes public, finished trials with a record that match, the newest first
    up to its limit; ids add to it; the list is by trial id, each with its digests."""
    ann = [finished(archive) for _ in range(4)]
    finished(archive, user="bob")
    finished(archive, outcome=Outcome.FAIL)
    finished(archive, kind=Kind.TRIAL)
    finished(archive, public=False)
    finished(archive, record=False, outcome=Outcome.SUCCESS)
    extra = finished(archive, kind=Kind.TRIAL, outcome=Outcome.FAIL)
    query = DataQuery(
        task=TASK, kind=Kind.DEMONSTRATION, outcome=Outcome.SUCCESS, user="ann", limit=3
    )
    pinned = resolve(DataSpec((extra,), query), archive)
    assert [p.trial for p in pinned] == [*ann[1:], extra]
    first = pinned[0]
    assert first == PinnedRecord(
        trial=ann[1], kind=Kind.DEMONSTRATION, task=TASK, seed=3, outcome=Outcome.SUCCESS,
        data_digest=f"{ann[1]:064x}", digest_topics=["/odom", "/cmd_vel"],
        mcap=f"sha256:{ann[1]:064x}", size=1000,
    )  # fmt: skip
    assert first.manifest_entry() == {
        "trial": ann[1],
        "data_digest": f"{ann[1]:064x}",
        "mcap": f"sha256:{ann[1]:064x}",
    }


def test_data_that_cannot_be_pinned_is_refused_with_the_reason(archive):
    """Nothing matched, too much (the lab's cap), an id that is missing, private or has no
    record, and data over the size limit: each is refused, saying which and why."""
    small = [finished(archive), finished(archive)]
    private = finished(archive, public=False)
    empty = finished(archive, record=False)
    big = finished(archive, size=3000)
    policy = DataPolicy(max_trials=2, max_bytes=2500)
    cases = [
        (DataSpec(query=DataQuery(task="pr2-table")), "matches no public, finished trial"),
        (DataSpec(query=DataQuery(kind=Kind.DEMONSTRATION)), "matches more than 2 trials"),
        (DataSpec(query=DataQuery(limit=5)), "query.limit is 5, more than this lab's limit"),
        (DataSpec((999,)), "trial 999 does not exist"),
        (DataSpec((private,)), f"trial {private} is not public"),
        (DataSpec((empty,)), f"trial {empty} has no record to learn from"),
        (DataSpec((big,)), "3000 bytes|0.0 MiB, more than this lab's limit of 0.0 MiB"),
    ]
    for spec, message in cases:
        with pytest.raises(InvalidData, match=message):
            resolve(spec, archive, policy)
    assert [p.trial for p in resolve(DataSpec(tuple(small)), archive, policy)] == small


def test_a_record_that_is_not_as_pinned_is_never_mounted(archive, tmp_path):
    """At run time each record is fetched and its data digest recomputed: a damaged blob or
    a digest that no longer matches ends the trial, and no data folder is left."""

    run = record(TypeRegistry.default(), tmp_path / "rec", manifest=True)
    mcap = run.summary.folder / "trial.mcap"
    blob = archive.store.put_file(mcap)
    good = PinnedRecord(
        trial=1, kind=Kind.TRIAL, task="pointmass", seed=5, outcome=Outcome.FAIL,
        data_digest=run.summary.data_digest, digest_topics=sorted(run.topics), mcap=blob,
        size=mcap.stat().st_size,
    )  # fmt: skip
    host = LabHost()
    changed = good.model_copy(update={"data_digest": "0" * 64})
    with pytest.raises(DataUnavailable, match="no longer has the data digest it was pinned"):
        materialize([changed], archive, host, tmp_path / "cache")
    missing = good.model_copy(update={"mcap": "sha256:" + "1" * 64})
    with pytest.raises(DataUnavailable, match="trial 1's record could not be read"):
        materialize([missing], archive, host, tmp_path / "cache")
    assert not (tmp_path / "cache" / "data").exists() or not any(
        p.name.endswith("json") for p in (tmp_path / "cache" / "data").rglob("*")
    )


def test_more_trial_ids_than_the_cap_are_refused_before_any_is_looked_up():
    """[data] naming more trials than max_trials is InvalidData at once: no id is looked
    up in the archive (an archive that fails every lookup shows it)."""

    class Untouchable:
        def trial(self, trial_id: int) -> object:
            raise AssertionError(f"trial {trial_id} was looked up")

    spec = DataSpec(tuple(range(1, 1002)))
    with pytest.raises(
        InvalidData, match="it names 1001 trials, more than this lab's limit of 200"
    ):
        resolve(spec, Untouchable(), DataPolicy())  # type: ignore[arg-type]
