"""The lab's signatures: a statement signed is checked by anyone with the public key; a
changed statement, another key, or a rotated-away key each fail or pass as they should."""

from __future__ import annotations

import json

import pytest
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric import ec, rsa

from repository.signing import (
    RECORD,
    KeyFileError,
    Keyring,
    Signature,
    SignatureError,
    file_digests,
    load_keys,
    record_statement,
    verify,
)

STATEMENT = {"schema": "labd.record/1", "trial": 7, "data_digest": "ab" * 32, "outcome": "fail"}


def test_a_signature_checks_with_the_labs_public_key_only(tmp_path):
    """What the lab signed verifies with its keys; with another lab's it does not."""
    lab = Keyring(tmp_path / "keys")
    signed = lab.sign(STATEMENT)
    verify(signed, lab.public_keys())
    again = Signature.from_json(json.loads(json.dumps(signed.to_json())))
    verify(again, lab.public_keys())
    other = Keyring(tmp_path / "other")
    with pytest.raises(SignatureError, match="not among the keys given"):
        verify(signed, other.public_keys())
    assert (tmp_path / "keys" / "signing.pem").stat().st_mode & 0o077 == 0


@pytest.mark.parametrize(
    ("field", "value"), [("outcome", "success"), ("trial", 8), ("key", "ed25519:0000000000000000")]
)
def test_a_changed_statement_fails(tmp_path, field, value):
    """Changing any field of the statement (the outcome, the trial, the key named) fails."""
    lab = Keyring(tmp_path / "keys")
    signed = lab.sign(STATEMENT)
    forged = Signature({**signed.statement, field: value}, signed.key, signed.value)
    with pytest.raises(SignatureError):
        verify(forged, lab.public_keys())


def test_rotation_keeps_old_signatures_verifiable(tmp_path):
    """After a rotation new statements use the new key, and old ones still verify."""
    lab = Keyring(tmp_path / "keys")
    before = lab.sign(STATEMENT)
    old = lab.current
    new = lab.rotate()
    assert new != old and Keyring(tmp_path / "keys").current == new
    after = lab.sign(STATEMENT)
    assert after.key == new
    keys = Keyring(tmp_path / "keys").public_keys()
    assert set(keys) == {old, new}
    verify(before, keys)
    verify(after, keys)


def test_file_digests_name_every_file(tmp_path):
    (tmp_path / "meta").mkdir()
    (tmp_path / "meta" / "info.json").write_text("{}")
    (tmp_path / "data.parquet").write_bytes(b"x")
    (tmp_path / "labd-signature.json").write_text("{}")
    found = file_digests(tmp_path, skip=frozenset({"labd-signature.json"}))
    assert sorted(found) == ["data.parquet", "meta/info.json"]
    assert all(d.startswith("sha256:") for d in found.values())


def test_keys_are_read_from_pem_or_the_labs_api_keys(tmp_path):
    """One PEM public key, or /api/keys' JSON, gives the keys by id."""
    lab = Keyring(tmp_path / "keys")
    keys = lab.public_keys()
    [pem] = keys.values()
    assert list(load_keys(pem.encode(), "lab.pem")) == [lab.current]
    listed = json.dumps({"current": lab.current, "keys": keys}).encode()
    assert list(load_keys(listed, "lab-keys.json")) == [lab.current]


def _pem(key) -> bytes:
    return key.public_key().public_bytes(
        serialization.Encoding.PEM, serialization.PublicFormat.SubjectPublicKeyInfo
    )


@pytest.mark.parametrize(
    ("data", "said"),
    [
        (b"", "is empty"),
        (b"\x89PNG\r\n\x1a\n", "holds neither a PEM key nor JSON"),
        (b"-----BEGIN PUBLIC KEY-----\nAAAA\n-----END PUBLIC KEY-----\n", "no PEM public key"),
        (b"{", "is not valid JSON"),
        (b"{}", 'without a "keys" object'),
        (b'{"keys": {}}', "lists no keys"),
        (b'{"keys": {"ed25519:0": 5}}', "lists ed25519:0 as int, not a PEM key"),
        ("rsa", "holds an RSA public key, and the lab signs with Ed25519"),
        ("ec", "holds an EC public key, and the lab signs with Ed25519"),
        ("mislabeled", "under the id ed25519:0000000000000000"),
    ],
)
def test_a_key_file_that_is_not_the_labs_keys_says_what_it_holds(tmp_path, data, said):
    """Whatever else a key file holds is a KeyFileError naming the file and what it
    holds, and saying where the lab's keys are."""
    if data == "rsa":
        data = _pem(rsa.generate_private_key(public_exponent=65537, key_size=2048))
    elif data == "ec":
        data = _pem(ec.generate_private_key(ec.SECP256R1()))
    elif data == "mislabeled":
        [pem] = Keyring(tmp_path / "keys").public_keys().values()
        data = json.dumps({"keys": {"ed25519:0000000000000000": pem}}).encode()
    with pytest.raises(KeyFileError) as caught:
        load_keys(data, "keys.file")
    assert str(caught.value).startswith("keys.file ")
    assert said in str(caught.value)
    assert "/api/keys" in str(caught.value)


def test_a_record_statement_names_the_whole_file():
    """A record's statement (labd.record/2) names the file's sha256 and size and the
    metrics, beside the digests."""
    statement = record_statement(
        trial=7, kind="trial", repository="/r", commit="c" * 40, task="t", seed=0,
        status="finished", outcome="fail", manifest_digest="m", data_digest="d",
        digest_topics=["/clock"], mcap="sha256:" + "a" * 64, mcap_size=10,
        metrics={"reward": 1.0}, finished=0.0,
    )  # fmt: skip
    assert statement["schema"] == RECORD == "labd.record/2"
    assert (statement["mcap"], statement["mcap_size"]) == ("sha256:" + "a" * 64, 10)
    assert statement["metrics"] == {"reward": 1.0}
