"""`labd verify`'s check of a record, offline: statements of both versions are held to the
whole file and to what it holds, recomputed."""

from __future__ import annotations

import json

import pytest

from labd.commands.verify import Mismatch, check
from labd.recorder import data_digest, read_manifest
from repository.digests import manifest_digest
from repository.signing import (
    RECORD,
    RECORD_V1,
    Keyring,
    file_digest,
    load_keys,
    record_statement,
)
from repository.well_known import SIGNATURE_SIDECAR
from tests.helpers.records import rewrite
from tests.labd.test_recorder import record

OUTCOME = {"status": "finished", "outcome": "fail", "reason": "ran out", "metrics": {"reward": 1.5}}


def signed(tmp_path, registry, schema, **lies):
    """A trial's record with its outcome.json, and the lab's signature of it beside it
    (``lies`` replace what the statement would say of it)."""
    run = record(registry, tmp_path / "run", manifest=True)
    mcap = rewrite(
        run.summary.path,
        tmp_path / "trial.mcap",
        add={"outcome.json": json.dumps(OUTCOME).encode()},
    )
    manifest = read_manifest(mcap)
    assert manifest is not None
    statement = record_statement(
        trial=7, kind="trial", repository="/r", commit="c" * 40, task="pointmass", seed=5,
        status="finished", outcome="fail",
        manifest_digest=manifest_digest(manifest),
        data_digest=data_digest(mcap, run.topics), digest_topics=sorted(run.topics),
        mcap=file_digest(mcap), mcap_size=mcap.stat().st_size, metrics=OUTCOME["metrics"],
        finished=0.0,
    )  # fmt: skip
    if schema == RECORD_V1:  # what the lab signed before: no size, no metrics
        statement = {k: v for k, v in statement.items() if k not in ("mcap_size", "metrics")}
        statement["schema"] = RECORD_V1
    keyring = Keyring(tmp_path / "keys")
    signature = keyring.sign({**statement, **lies})
    sidecar = mcap.with_name(mcap.name + SIGNATURE_SIDECAR)
    sidecar.write_text(json.dumps(signature.to_json()))
    [pem] = keyring.public_keys().values()
    return mcap, load_keys(pem.encode(), "lab.pem")


@pytest.mark.parametrize("schema", [RECORD, RECORD_V1])
def test_a_record_verifies_under_either_statement(tmp_path, registry, schema):
    """A record the lab signed verifies with a statement of this version or the last."""
    mcap, keys = signed(tmp_path, registry, schema)
    assert check(mcap, keys)["verified"] is True


@pytest.mark.parametrize("schema", [RECORD, RECORD_V1])
def test_an_edited_record_fails_under_either_statement(tmp_path, registry, schema):
    """A byte appended to the file fails against both versions: /1 named the file's
    sha256 too."""
    mcap, keys = signed(tmp_path, registry, schema)
    with mcap.open("ab") as out:
        out.write(b"\0")
    with pytest.raises(Mismatch, match="the file's bytes differ from what the lab signed"):
        check(mcap, keys)


@pytest.mark.parametrize(
    ("lie", "said"),
    [
        ({"data_digest": "e" * 64}, "data_digest: the record's data digest is"),
        ({"outcome": "success"}, "outcome: the record says 'fail', not 'success'"),
        ({"metrics": {"reward": 1e9}}, "metrics: the record's differ in reward"),
    ],
)
def test_a_statement_that_says_other_than_its_record_fails(tmp_path, registry, lie, said):
    """A signed statement whose digest, outcome or metrics the file does not hold (a
    worker's word signed before filings were checked) fails, though the bytes match."""
    mcap, keys = signed(tmp_path, registry, RECORD, **lie)
    with pytest.raises(Mismatch) as caught:
        check(mcap, keys)
    assert said in str(caught.value)
    assert "the file's bytes differ" not in str(caught.value)
