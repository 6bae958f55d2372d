"""The lab's signatures: a statement signed is checked by anyone with the public key; a
changed statement, another key, or a rotated-away key each fail or pass as they should."""

from __future__ import annotations

import json

import pytest

from repository.signing import Keyring, Signature, SignatureError, file_digests, verify

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
