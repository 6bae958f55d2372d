"""The lab's signatures: a filed record, or an export, checkable offline with a public key.

The lab signs a **statement**, a small JSON object saying what it vouches for, with
Ed25519 (``cryptography``) over its canonical JSON (``repository.digests``), so
anyone with the lab's public key can check one, with no server.

- A record's statement (``labd.record/2``) names the trial, its commit and task, how it
  ended and its metrics, the manifest digest, the data digest (every observation and
  action), the digest topics, and the record's file itself: ``mcap`` is the sha256 of
  its bytes (the blob's name in the archive) and ``mcap_size`` their number. So the
  signature covers the whole file: its attachments (the outcome, the logs, the model),
  every topic, every byte. A remote worker's record is signed only after the lab read
  it and found what the worker claimed (``scheduler.filing``).
- ``labd.record/1``, before, said the same without ``mcap_size`` and ``metrics``; its
  ``mcap`` was the file's sha256 too, but checkers compared only the manifest and data
  digests, so an edited attachment or a dropped topic still "verified". ``labd verify``
  now checks a /1 statement's ``mcap`` as well, so what /1 signed is held to the whole
  file too; it cannot vouch for the metrics, which /1 never named.
- An export's statement (``labd.export/1``) lists the digest of each of its files; one
  of a single trial names it (``trial``), one of many names each (``trials``).

Keys live in a folder (``DATA/keys``): the signing key (``signing.pem``, readable by the
lab only) and every public key the lab ever used (``ed25519-<id>.pub.pem``). Rotating
makes a new signing key and keeps the old public keys, so old signatures still check.
A key's id is ``ed25519:`` and the first 16 hex digits of the sha256 of its raw bytes.
Someone checking a signature gives the public keys as one PEM key or as what the lab's
``/api/keys`` answers (``load_keys``); anything else is a ``KeyFileError`` saying so.
"""

from __future__ import annotations

import base64
import hashlib
import json
import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from cryptography.exceptions import InvalidSignature, UnsupportedAlgorithm
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric import dsa, ec, ed448, rsa, x25519
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey, Ed25519PublicKey

from repository.digests import canonical_json
from repository.errors import ArchiveError
from repository.units import MiB, moment

RECORD = "labd.record/2"  # what a record's statement says it is (the whole file, metrics)
RECORD_V1 = "labd.record/1"  # the manifest and data digests; mcap named the file unchecked
RECORDS = frozenset({RECORD, RECORD_V1})  # the record statements a checker reads
EXPORT = "labd.export/1"
SIGNING = "signing.pem"


class SignatureError(ArchiveError):
    """A signature does not check: the message says what differs, or which key is missing."""


class KeyFileError(ArchiveError):
    """A file given as the lab's public keys is not: the message says what it holds."""

    def __init__(self, source: str, reason: str) -> None:
        self.source = source
        self.reason = reason
        super().__init__(
            f"{source} {reason}; give the lab's public keys: what its /api/keys answers"
            " (curl -s LAB/api/keys > lab-keys.json), or one Ed25519 public key in PEM"
        )


def key_id(public: Ed25519PublicKey) -> str:
    raw = public.public_bytes(serialization.Encoding.Raw, serialization.PublicFormat.Raw)
    return "ed25519:" + hashlib.sha256(raw).hexdigest()[:16]


def public_pem(public: Ed25519PublicKey) -> str:
    return public.public_bytes(
        serialization.Encoding.PEM, serialization.PublicFormat.SubjectPublicKeyInfo
    ).decode()


def load_public(pem: str | bytes) -> Ed25519PublicKey:
    key = serialization.load_pem_public_key(pem.encode() if isinstance(pem, str) else pem)
    if not isinstance(key, Ed25519PublicKey):
        raise SignatureError("the key is not an Ed25519 public key")
    return key


def load_keys(data: bytes, source: str) -> dict[str, Ed25519PublicKey]:
    """The public keys in ``data`` (read from ``source``), by id: one PEM public key, or
    the JSON of ``/api/keys`` (``{"keys": {ID: PEM}}``). ``KeyFileError`` if it is
    neither, or a key is not Ed25519, or is listed under another key's id."""
    text = data.strip()
    if not text:
        raise KeyFileError(source, "is empty")
    if text.startswith(b"{"):
        try:
            listed = json.loads(text)
        except (ValueError, UnicodeDecodeError) as err:
            raise KeyFileError(source, f"is not valid JSON ({err})") from None
        if not isinstance(listed, dict) or not isinstance(listed.get("keys"), dict):
            raise KeyFileError(source, 'is JSON without a "keys" object of PEM keys by id')
        keys = {}
        for given, pem in listed["keys"].items():
            if not isinstance(pem, str):
                raise KeyFileError(source, f"lists {given} as {type(pem).__name__}, not a PEM key")
            key = _public(pem.encode(), source, f"lists {given} as")
            if key_id(key) != given:
                raise KeyFileError(source, f"lists key {key_id(key)} under the id {given}")
            keys[given] = key
        if not keys:
            raise KeyFileError(source, "lists no keys")
        return keys
    key = _public(text, source, "holds")
    return {key_id(key): key}


def _public(pem: bytes, source: str, says: str) -> Ed25519PublicKey:
    """One PEM public key, which must be Ed25519 (``KeyFileError`` naming what it is)."""
    if not pem.startswith(b"-----BEGIN "):
        raise KeyFileError(source, f"{says} neither a PEM key nor JSON")
    try:
        key = serialization.load_pem_public_key(pem)
    except (ValueError, TypeError, UnsupportedAlgorithm) as err:
        first = str(err).split(".")[0]
        raise KeyFileError(
            source, f"{says} no PEM public key the lab could read ({first})"
        ) from None
    if not isinstance(key, Ed25519PublicKey):
        kind = next((name for cls, name in _KINDS if isinstance(key, cls)), "another kind of")
        raise KeyFileError(source, f"{says} {kind} public key, and the lab signs with Ed25519")
    return key


_KINDS = (  # what a PEM public key that is not Ed25519 is, in words
    (rsa.RSAPublicKey, "an RSA"),
    (ec.EllipticCurvePublicKey, "an EC"),
    (dsa.DSAPublicKey, "a DSA"),
    (ed448.Ed448PublicKey, "an Ed448"),
    (x25519.X25519PublicKey, "an X25519"),
)


@dataclass(frozen=True)
class Signature:
    """A statement, the id of the key that signed it, and the signature (base64)."""

    statement: dict[str, Any]
    key: str
    value: str

    def to_json(self) -> dict[str, Any]:
        return {"statement": self.statement, "key": self.key, "signature": self.value}

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> Signature:
        try:
            return cls(dict(data["statement"]), str(data["key"]), str(data["signature"]))
        except (KeyError, TypeError, ValueError) as err:
            raise SignatureError(f"not a labd signature ({err!r} missing or wrong)") from None


class Keyring:
    """The lab's keys in ``folder``: one to sign with, and every public key it used."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        folder.mkdir(mode=0o700, parents=True, exist_ok=True)
        path = folder / SIGNING
        if not path.exists():
            self._write_new()
        loaded = serialization.load_pem_private_key(path.read_bytes(), password=None)
        if not isinstance(loaded, Ed25519PrivateKey):
            raise SignatureError(f"{path} is not an Ed25519 private key")
        self._private: Ed25519PrivateKey = loaded
        self.current = key_id(loaded.public_key())

    def _write_new(self) -> Ed25519PrivateKey:
        private = Ed25519PrivateKey.generate()
        pem = private.private_bytes(
            serialization.Encoding.PEM,
            serialization.PrivateFormat.PKCS8,
            serialization.NoEncryption(),
        )
        tmp = self.folder / f".{SIGNING}.{os.getpid()}"
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        with os.fdopen(fd, "wb") as out:
            out.write(pem)
        public = private.public_key()
        (self.folder / _public_name(key_id(public))).write_text(public_pem(public))
        tmp.replace(self.folder / SIGNING)
        return private

    def rotate(self) -> str:
        """Sign with a new key from now on; the old public keys stay. The new key's id."""
        self._private = self._write_new()
        self.current = key_id(self._private.public_key())
        return self.current

    def public_keys(self) -> dict[str, str]:
        """Every public key the lab used, by id (PEM)."""
        keys = {}
        for path in sorted(self.folder.glob("ed25519-*.pub.pem")):
            key = load_public(path.read_text())
            keys[key_id(key)] = path.read_text()
        return keys

    def sign(self, statement: Mapping[str, Any]) -> Signature:
        body = {**statement, "key": self.current}
        value = base64.b64encode(self._private.sign(canonical_json(body).encode())).decode()
        return Signature(body, self.current, value)


def _public_name(kid: str) -> str:
    return f"ed25519-{kid.split(':', 1)[1]}.pub.pem"


def verify(signature: Signature, keys: Mapping[str, str | Ed25519PublicKey]) -> None:
    """Check ``signature`` against the public keys (by id); ``SignatureError`` if not."""
    key = keys.get(signature.key)
    if key is None:
        raise SignatureError(
            f"signed with key {signature.key}, which is not among the keys given"
            f" ({', '.join(keys) or 'none'}); get the lab's keys from its /api/keys"
        )
    public = load_public(key) if isinstance(key, str) else key
    if signature.statement.get("key") != signature.key:
        raise SignatureError("the statement names another key than the signature's")
    try:
        public.verify(
            base64.b64decode(signature.value), canonical_json(signature.statement).encode()
        )
    except (InvalidSignature, ValueError):
        raise SignatureError(
            "the signature does not match its statement: the statement was changed, or"
            " another key made it"
        ) from None


def record_statement(
    *,
    trial: int,
    kind: str,
    repository: str,
    commit: str | None,
    task: str,
    seed: int,
    status: str,
    outcome: str | None,
    manifest_digest: str | None,
    data_digest: str | None,
    digest_topics: list[str] | None,
    mcap: str | None,
    mcap_size: int | None,
    metrics: Mapping[str, Any] | None,
    finished: float,
) -> dict[str, Any]:
    """What the lab vouches for when it files a trial's record (``labd.record/2``):
    ``mcap`` is the sha256 of the record's bytes, ``mcap_size`` their number."""
    return {
        "schema": RECORD,
        "trial": trial,
        "kind": kind,
        "repository": repository,
        "commit": commit,
        "task": task,
        "seed": seed,
        "status": status,
        "outcome": outcome,
        "manifest_digest": manifest_digest,
        "data_digest": data_digest,
        "digest_topics": digest_topics,
        "mcap": mcap,
        "mcap_size": mcap_size,
        "metrics": dict(metrics) if metrics is not None else None,
        "finished": moment(finished).isoformat(),
    }


def file_digest(path: Path) -> str:
    """``sha256:HEX`` of the file's bytes, read a MiB at a time."""
    sha = hashlib.sha256()
    with path.open("rb") as stream:
        while chunk := stream.read(MiB):
            sha.update(chunk)
    return f"sha256:{sha.hexdigest()}"


def file_digests(folder: Path, *, skip: frozenset[str] = frozenset()) -> dict[str, str]:
    """``sha256:HEX`` of every file under ``folder``, by relative path (``skip`` aside)."""
    digests = {}
    for path in sorted(p for p in folder.rglob("*") if p.is_file()):
        name = path.relative_to(folder).as_posix()
        if name in skip:
            continue
        digests[name] = file_digest(path)
    return digests
