"""``labd verify FILE|DIR``: check a record or an export against the lab's signature, offline.

    labd verify trial-12.mcap --key lab-keys.json      a record (its signature beside it,
                                                         in trial-12.mcap.sig.json)
    labd verify trial-12-lerobot/ --key lab-keys.json   an export (labd-signature.json in it)
    labd keys rotate --data DIR                          the operator's: sign with a new key

``--key`` is a PEM public key, or what the lab's ``/api/keys`` answers (every key it
used); ``--server URL`` fetches that instead. A record is checked by recomputing its
manifest digest and data digest from the MCAP file itself; an export by recomputing the
digest of every file. The exit code is 0 when everything checks, 6 when something does
not (the message says what was changed), 2 for a usage error.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import struct
from pathlib import Path
from typing import Any

from mcap.exceptions import McapError
from zstandard import ZstdError

from labd.commands.common import ExitCode, emit, fail, json_option
from labd.config import DATA
from labd.recorder import canonical_json, data_digest, read_manifest
from repository.errors import ArchiveError
from repository.signing import (
    EXPORT,
    RECORD,
    Keyring,
    Signature,
    SignatureError,
    file_digests,
    key_id,
    load_public,
    verify,
)
from scheduler.client import ApiClient
from scheduler.errors import RemoteError

SIDECAR = ".sig.json"  # a record's signature, beside it: trial-12.mcap.sig.json
EXPORT_SIGNATURE = "labd-signature.json"


def add_parser(commands: Any) -> None:
    p = commands.add_parser("verify", help="check a record or an export against its signature")
    p.add_argument("target", type=Path, metavar="FILE|DIR", help="an MCAP record or an export")
    p.add_argument("--key", type=Path, help="the lab's public keys: a PEM file or /api/keys JSON")
    p.add_argument("--server", help="fetch the keys from this lab instead (online)")
    p.add_argument(
        "--signature", type=Path, help="a record's signature (default: FILE.sig.json beside it)"
    )
    json_option(p)

    keys = commands.add_parser("keys", help="the operator's: the keys the lab signs with")
    actions = keys.add_subparsers(dest="action", required=True)
    rotate = actions.add_parser("rotate", help="sign with a new key from now on (old ones stay)")
    rotate.add_argument(
        "--data", type=Path, default=DATA, help="the lab's data folder (default: %(default)s)"
    )
    json_option(rotate)


def main(args: argparse.Namespace) -> int:
    if args.command == "keys":
        return _rotate(args)
    try:
        keys = _keys(args)
        found = check(args.target, keys, args.signature)
    except (SignatureError, Mismatch) as err:
        return fail(args, str(err), ExitCode.INVALID)
    except (ArchiveError, RemoteError, OSError, ValueError) as err:
        return fail(args, str(err))
    emit(args, found, lambda: [found["summary"]])
    return 0


class Mismatch(Exception):
    """The signature is the lab's, but what it vouches for was changed."""


def check(target: Path, keys: dict[str, Any], signature: Path | None = None) -> dict[str, Any]:
    """Verify ``target`` (a record or an export); what was checked (``Mismatch`` if not)."""
    if target.is_dir():
        return _export(target, keys)
    return _record(target, keys, signature or target.with_name(target.name + SIDECAR))


def _record(mcap: Path, keys: dict[str, Any], sidecar: Path) -> dict[str, Any]:
    if not sidecar.exists():
        raise ValueError(
            f"no signature for {mcap}: expected {sidecar} (`labd download` writes it; a"
            " record is signed when a lab files it, never by labd run)"
        )
    signed = Signature.from_json(json.loads(sidecar.read_text()))
    verify(signed, keys)
    statement = signed.statement
    if statement.get("schema") != RECORD:
        raise ValueError(f"{sidecar} signs {statement.get('schema')}, not a record")
    try:
        manifest = read_manifest(mcap)
        data = data_digest(mcap, statement.get("digest_topics") or [])
    except (McapError, ZstdError, struct.error, UnicodeDecodeError, ValueError) as err:
        raise Mismatch(
            f"{mcap} can no longer be read as the record the lab signed: {err}"
        ) from None
    changed = []
    if manifest is None:
        changed.append("the record holds no manifest")
    else:
        digest = hashlib.sha256(canonical_json(manifest).encode()).hexdigest()
        if digest != statement["manifest_digest"]:
            changed.append(
                f"the manifest (its digest is {digest}, signed {statement['manifest_digest']})"
            )
    if data != statement["data_digest"]:
        changed.append(
            "the observations and actions (the data digest is"
            f" {data}, signed {statement['data_digest']})"
        )
    if changed:
        raise Mismatch(f"{mcap} was changed after the lab signed it: " + "; ".join(changed))
    return {
        "verified": True,
        "kind": "record",
        "trial": statement["trial"],
        "key": signed.key,
        "summary": (
            f"{mcap}: verified: trial {statement['trial']} ({statement['task']},"
            f" {statement['outcome'] or statement['status']}), signed by {signed.key}"
        ),
    }


def _export(folder: Path, keys: dict[str, Any]) -> dict[str, Any]:
    path = folder / EXPORT_SIGNATURE
    if not path.exists():
        raise ValueError(f"{folder} holds no {EXPORT_SIGNATURE}: not a signed export")
    signed = Signature.from_json(json.loads(path.read_text()))
    verify(signed, keys)
    statement = signed.statement
    if statement.get("schema") != EXPORT:
        raise ValueError(f"{path} signs {statement.get('schema')}, not an export")
    signed_files: dict[str, str] = statement["files"]
    present = file_digests(folder, skip=frozenset({EXPORT_SIGNATURE}))
    changed = sorted(n for n in signed_files if n in present and present[n] != signed_files[n])
    missing = sorted(set(signed_files) - set(present))
    extra = sorted(set(present) - set(signed_files))
    if changed or missing or extra:
        parts = [
            f"{label}: {', '.join(names)}"
            for label, names in (("changed", changed), ("missing", missing), ("added", extra))
            if names
        ]
        raise Mismatch(f"{folder} is not the export the lab signed: " + "; ".join(parts))
    return {
        "verified": True,
        "kind": "export",
        "trial": statement["trial"],
        "key": signed.key,
        "summary": (
            f"{folder}: verified: the {statement['format']} export of trial"
            f" {statement['trial']}, {len(signed_files)} files, signed by {signed.key}"
        ),
    }


def _keys(args: argparse.Namespace) -> dict[str, Any]:
    if args.key is not None:
        text = args.key.read_text()
        if text.lstrip().startswith("{"):
            return dict(json.loads(text)["keys"])
        public = load_public(text)
        return {key_id(public): public}
    if args.server:
        with ApiClient(args.server) as client:
            return dict(client.request("GET", "/api/keys").json()["keys"])
    raise ValueError("give the lab's keys: --key FILE (from its /api/keys), or --server URL")


def _rotate(args: argparse.Namespace) -> int:
    keyring = Keyring((args.data / "keys").resolve())
    old = keyring.current
    new = keyring.rotate()
    text = f"the lab signs with {new} from now on; {old} still verifies what it signed"
    emit(args, {"current": new, "previous": old}, lambda: [text])
    return 0
