"""Records, their verification and the lab's signatures, attacked (issue 24, "Records").

A real `labd serve` with no worker of its own, and a real `labd worker` on the same
machine that runs two trials (seeds 0 and 1) and files them: the lab checks each filing
and signs it. Then the attacks, with the tools anyone has: the records downloaded with
`labd download` and edited with mcap's own writer (an outcome, a log, a topic dropped, a
300 MiB attachment added), a chunk of 64 KiB that decompresses to 2 GiB, key files that
are not the lab's keys, an export of both trials, and a worker's token used to file a
claimed trial with what its record does not hold.
"""

from __future__ import annotations

import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import pytest
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric import ec, rsa

from labd.recorder import data_digest
from scheduler.remote import PROTOCOL, PROTOCOL_HEADER
from tests.faults.conftest import Served
from tests.faults.slow import controller
from tests.faults.test_remote_worker import RemoteWorker
from tests.helpers.githttp import GitRepo
from tests.helpers.records import GiB, chunk_record, rewrite, with_chunk, zstd_bomb

pytestmark = pytest.mark.integration
MiB = 1 << 20
MEMORY = 3 * GiB // 2  # the address space `labd verify` and `labd replay` get under attack


@dataclass
class Archive:
    """A lab, its worker's token, two filed trials and their records with signatures."""

    lab: Served
    worker: str  # a worker's token
    trials: list[dict[str, Any]]
    records: list[Path]  # trial-N.mcap, each with trial-N.mcap.sig.json beside it
    keys: Path  # what /api/keys answered
    folder: Path

    def labd(self, *args: str) -> subprocess.CompletedProcess[str]:
        return self.lab.labd(*args, check=False)

    def verify(self, target: Path, *more: str) -> subprocess.CompletedProcess[str]:
        return self.labd("verify", str(target), "--key", str(self.keys), *more)


@pytest.fixture(scope="module")
def archive(tmp_path_factory: pytest.TempPathFactory, cache: Path) -> Iterator[Archive]:
    folder = tmp_path_factory.mktemp("records")
    lab = Served(
        folder / "data",
        cache,
        "--no-robots",
        "--workers",
        "0",
        "--lease",
        "30",
        "--allow-local-repos",
    )
    lab.token = lab.add_user("alice")
    worker_token = lab.add_user("w1", "--worker")
    lab.start()
    worker = RemoteWorker(lab, worker_token, folder / "worker", cache)
    try:
        repo = GitRepo.create(folder / "repo", controller(5)).path
        ids = [lab.submit(repo, seed=seed)["id"] for seed in (0, 1)]
        trials = lab.wait_ended(ids, 150)
        assert [t["outcome"] for t in trials] == ["fail", "fail"], trials
        records = []
        for trial in trials:
            path = folder / f"trial-{trial['id']}.mcap"
            lab.labd("download", str(trial["id"]), "-o", str(path))
            records.append(path)
        keys = folder / "lab-keys.json"
        keys.write_text(httpx.get(f"{lab.server}/api/keys", timeout=30).text)
    finally:
        output = worker.stop()
    assert worker.process.returncode == 0, output
    try:
        yield Archive(lab, worker_token, trials, records, keys, folder)
    finally:
        lab.stop()


def no_traceback(done: subprocess.CompletedProcess[str]) -> str:
    assert "Traceback" not in done.stderr, done.stderr
    return done.stderr


# -- 1. the signature covers the whole file ------------------------------------------------


def test_an_untouched_record_verifies(archive: Archive):
    """A record as the lab filed it verifies, with its trial, outcome and key named."""
    for trial, record in zip(archive.trials, archive.records, strict=True):
        done = archive.verify(record)
        assert done.returncode == 0, done.stderr
        assert f"verified: trial {trial['id']} (icreate-maze, fail)" in done.stdout


ELSEWHERE = "so what changed is elsewhere: an attachment (a log, the model)"
EDITS = {  # the edit, and what verify must say of it
    "outcome": (
        {"attachments": {"outcome.json": lambda d: d.replace(b'"fail"', b'"success"')}},
        "outcome: the record says 'success', not 'fail'",
    ),
    "log": ({"attachments": {"controller.stderr.log": lambda d: d + b"all is well\n"}}, ELSEWHERE),
    "topic": ({"drop": ["/rosout"]}, ELSEWHERE),
    "attachment": ({"add": {"big.bin": bytes(300 * MiB)}}, "may hold at most 256 MiB"),
}


@pytest.mark.parametrize("edit", sorted(EDITS))
def test_a_record_edited_after_signing_does_not_verify(archive: Archive, edit: str):
    """An outcome, a log or an attachment edited, a topic dropped or 300 MiB added: the
    record no longer verifies, and verify says its bytes are not what the lab signed."""
    original = archive.records[0]
    change, said = EDITS[edit]
    edited = rewrite(original, archive.folder / f"edited-{edit}.mcap", **change)
    assert edited.read_bytes() != original.read_bytes()
    signature = original.with_name(original.name + ".sig.json")
    started = time.monotonic()
    done = archive.verify(edited, "--signature", str(signature))
    took = time.monotonic() - started
    assert done.returncode == 6, (done.returncode, done.stdout, done.stderr)
    no_traceback(done)
    assert "was changed after the lab signed it: the file's bytes differ from what the lab" in (
        done.stderr
    ), done.stderr
    assert said in done.stderr, done.stderr
    print(f"\n{edit}: {edited.stat().st_size:,} bytes, refused in {took:.1f} s: {done.stderr}")


# -- 2. a chunk that decompresses to 2 GiB --------------------------------------------------


def limited(*args: str) -> subprocess.CompletedProcess[str]:
    """`labd ARGS` with its address space capped at ``MEMORY``: a 2 GiB allocation fails.
    (The shell sets the cap: no code runs between fork and exec in the test's process.)"""
    cap = f'ulimit -v {MEMORY // 1024} && exec "$@"'
    return subprocess.run(
        ["bash", "-c", cap, "labd", sys.executable, "-m", "labd", *args],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )


@pytest.fixture(scope="module")
def bombed(archive: Archive) -> Path:
    """The first record with a chunk of about 64 KiB that decompresses to 2 GiB of zeros."""
    bomb = zstd_bomb(2 * GiB)
    assert len(bomb) < 128 * 1024, len(bomb)
    print(f"\na zstd frame of {len(bomb):,} bytes decompressing to 2 GiB")
    path = archive.folder / "bombed.mcap"
    return with_chunk(archive.records[0], path, chunk_record(bomb, 2 * GiB))


@pytest.mark.parametrize("command", ["verify", "replay"])
def test_a_chunk_declaring_2_gib_is_refused_unread(archive: Archive, bombed: Path, command: str):
    """`labd verify` and `labd replay` refuse a record whose chunk declares 2 GiB with an
    error naming the limit, within an address space far smaller than the chunk."""
    started = time.monotonic()
    if command == "verify":
        signature = archive.records[0].with_name(archive.records[0].name + ".sig.json")
        args = ["--key", str(archive.keys), "--signature", str(signature)]
        done = limited("verify", str(bombed), *args)
        assert done.returncode == 6, (done.returncode, done.stderr)
    else:
        done = limited("replay", str(bombed))
        assert done.returncode == 2, (done.returncode, done.stderr)
    print(f"\n{command}: refused in {time.monotonic() - started:.1f} s: {done.stderr}")
    no_traceback(done)
    assert "MemoryError" not in done.stderr
    assert "2048 MiB" in done.stderr and "256 MiB" in done.stderr, done.stderr


# -- 3. key files and exports of many trials -------------------------------------------------


def public_pem(key: Any) -> bytes:
    return bytes(
        key.public_key().public_bytes(
            serialization.Encoding.PEM, serialization.PublicFormat.SubjectPublicKeyInfo
        )
    )


KEY_FILES = {
    "garbage": b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR\xff\xfe",
    "empty": b"",
    "rsa": public_pem(rsa.generate_private_key(public_exponent=65537, key_size=2048)),
    "ec": public_pem(ec.generate_private_key(ec.SECP256R1())),
    "json-without-keys": b"{}",
    "json-list": b"[1, 2]",
    "json-with-a-bad-key": b'{"keys": {"ed25519:0000000000000000": "not a key"}}',
}


@pytest.mark.parametrize("name", sorted(KEY_FILES))
def test_a_key_file_that_is_not_the_labs_keys_is_a_usage_error(archive: Archive, name: str):
    """A garbage, empty, RSA, EC or malformed JSON key file is a usage error (2) that
    says what the file should be; never a traceback, never "changed"."""
    keys = archive.folder / f"keys-{name}"
    keys.write_bytes(KEY_FILES[name])
    done = archive.labd("verify", str(archive.records[0]), "--key", str(keys))
    assert done.returncode == 2, (done.returncode, done.stdout, done.stderr)
    no_traceback(done)
    assert str(keys) in done.stderr and "/api/keys" in done.stderr, done.stderr


def test_a_signed_export_of_two_trials_verifies_and_names_changes(archive: Archive):
    """The lab's export of two trials verifies, naming both; a file changed or added
    afterwards is named and the export no longer verifies."""
    ids = [str(t["id"]) for t in archive.trials]
    out = archive.folder / "export-two"
    made = archive.labd("export", "--trials", *ids, "--format", "parquet", "-o", str(out))
    assert made.returncode == 0, made.stderr
    done = archive.verify(out)
    assert done.returncode == 0, (done.returncode, done.stdout, done.stderr)
    assert f"trials {', '.join(ids)}" in done.stdout, done.stdout
    data = out / "data.parquet"
    data.write_bytes(data.read_bytes() + b"\0")
    (out / "notes.txt").write_text("added later\n")
    done = archive.verify(out)
    assert done.returncode == 6, (done.returncode, done.stdout, done.stderr)
    no_traceback(done)
    assert "changed: data.parquet; added: notes.txt" in done.stderr, done.stderr


# -- 4. a worker's filing is checked before the lab signs it ---------------------------------


def test_a_workers_filing_is_checked_against_its_record_before_signing(archive: Archive):
    """A worker filing its claimed trial with another trial's digest or record, a reward
    of 1e9, another outcome, fewer digest topics, a wrong size or verdict, or a success
    without a record is refused with 422 saying why, and nothing is signed; the filing
    its record bears out is signed, and verifies."""
    lab = archive.lab
    first, second = archive.trials
    rerun = httpx.post(
        f"{lab.server}/api/trials/{first['id']}/rerun",
        headers={"Authorization": f"Bearer {lab.token}"},
        timeout=30,
    )
    assert rerun.status_code == 201, rerun.text
    worker = httpx.Client(
        base_url=lab.server,
        headers={"Authorization": f"Bearer {archive.worker}", PROTOCOL_HEADER: str(PROTOCOL)},
        timeout=60,
    )
    with worker:
        claim = worker.post("/api/workers/claim", json={"worker": "evil"})
        assert claim.status_code == 200, claim.text
        trial_id = claim.json()["id"]
        assert trial_id == rerun.json()["id"]
        a, c = (worker.get(f"/api/workers/trials/{t['id']}").json() for t in (first, second))
        honest = {
            key: a[key]
            for key in (
                "status", "outcome", "reason", "manifest", "manifest_digest", "data_digest",
                "digest_topics", "metrics", "backend", "wall_seconds", "mcap", "mcap_size",
                "stdout", "stderr",
            )
        }  # fmt: skip
        honest.update(reproduced=True, divergence=None)
        clock_only = data_digest(archive.records[0], ["/clock"])
        attacks = {
            "another trial's data digest": ({"data_digest": c["data_digest"]}, "data_digest"),
            "another trial's record": (
                {k: c[k] for k in honest if k in c and k not in ("reproduced", "divergence")},
                "manifest",
            ),
            "a reward of 1e9": (
                {"metrics": {**a["metrics"], "reward": 1e9}},
                "metrics",
            ),
            "another outcome": ({"outcome": "success"}, "outcome"),
            "fewer digest topics": (
                {"digest_topics": ["/clock"], "data_digest": clock_only},
                "digest_topics",
            ),
            "a wrong size": ({"mcap_size": a["mcap_size"] + 1}, "mcap_size"),
            "a wrong verdict": (
                {"reproduced": False, "divergence": "diverged at tick 1"},
                "reproduced",
            ),
            "a success without a record": (
                {
                    "outcome": "success",
                    "metrics": {"reward": 1e9},
                    "mcap": None,
                    "mcap_size": None,
                    "manifest_digest": None,
                    "data_digest": None,
                },
                "record",
            ),
        }
        for what, (change, named) in attacks.items():
            filing = {**honest, **change}
            answer = worker.post(
                f"/api/workers/trials/{trial_id}/finish",
                json={"worker": "evil", "filing": filing},
            )
            assert answer.status_code == 422, (what, answer.status_code, answer.text)
            print(f"\n{what}: {answer.json()['error']}")
            assert named in answer.json()["error"], (what, answer.text)
            row = lab.trial(trial_id)
            assert (row["status"], row["signature"]) == ("running", None), (what, row)
        started = time.monotonic()
        answer = worker.post(
            f"/api/workers/trials/{trial_id}/finish", json={"worker": "evil", "filing": honest}
        )
        print(f"\nthe honest filing, checked and signed in {time.monotonic() - started:.2f} s")
        assert answer.status_code == 200 and answer.json() == {"filed": True}, answer.text
    row = lab.trial(trial_id)
    assert (row["status"], row["outcome"], row["reproduced"]) == ("finished", "fail", True)
    statement = row["signature"]["statement"]
    assert statement["schema"] == "labd.record/2"
    assert statement["metrics"] == a["metrics"] and statement["mcap_size"] == a["mcap_size"]
    path = archive.folder / f"trial-{trial_id}.mcap"
    assert lab.labd("download", str(trial_id), "-o", str(path)).returncode == 0
    done = archive.verify(path)
    assert done.returncode == 0, done.stderr
    assert f"verified: trial {trial_id} (icreate-maze, fail)" in done.stdout


def test_verify_fetches_the_keys_from_labd_server(archive: Archive) -> None:
    """With no --key, `labd verify` asks the lab that $LABD_SERVER names for its keys."""
    done = archive.labd("verify", str(archive.records[0]))  # LABD_SERVER is the lab's
    assert done.returncode == 0, done.stderr
    assert "verified" in done.stdout.lower() or "signed" in done.stdout.lower(), done.stdout
