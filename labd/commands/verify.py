"""``labd verify FILE|DIR``: check a record or an export against the lab's signature, offline.

    labd verify trial-12.mcap --key lab-keys.json      a record (its signature beside it,
                                                         in trial-12.mcap.sig.json)
    labd verify trial-12-lerobot/ --key lab-keys.json   an export (labd-signature.json in it)
    labd keys rotate --data DIR                          the operator's: sign with a new key

``--key`` is a PEM public key, or what the lab's ``/api/keys`` answers (every key it
used); ``--server URL`` fetches that instead. A record is checked whole: the sha256 and
size of its file against those the lab signed (``repository.signing``), and then what
it holds against what the lab signed of it, recomputed from the file: the manifest
digest, the data digest and, for a trial, the outcome and metrics its ``outcome.json``
says. So a record whose bytes changed is refused, and the message says which of those
parts changed too, or that the change is elsewhere (a log, the model, a topic outside
the data digest, bytes added). A file is read within the archive's limits
(``repository.mcapfile``), so a chunk that would decompress to gigabytes is refused
unread. An export is checked by recomputing the digest of every file. The exit code is
0 when everything checks, 6 when something does not (the message says what was
changed), 2 for a usage error (a key file that is not the lab's keys, say).
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path
from typing import Any

from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PublicKey

from labd.commands import settings
from labd.commands.common import ExitCode, emit, fail, json_option
from labd.trial import LabHost
from repository.errors import ArchiveError
from repository.masking import mask_url
from repository.signing import (
    EXPORT,
    RECORDS,
    Keyring,
    Signature,
    SignatureError,
    file_digest,
    file_digests,
    load_keys,
    verify,
)
from repository.well_known import EXPORT_SIGNATURE, SIGNATURE_SIDECAR
from scheduler.client import ApiClient
from scheduler.errors import RemoteError, TrialError
from scheduler.filing import Claims, record_differences

SIDECAR = ".sig.json"  # a record's signature, beside it: trial-12.mcap.sig.json


def add_parser(commands: Any) -> None:
    p = commands.add_parser("verify", help="check a record or an export against its signature")
    p.add_argument("target", type=Path, metavar="FILE|DIR", help="an MCAP record or an export")
    p.add_argument("--key", type=Path, help="the lab's public keys: a PEM file or /api/keys JSON")
    p.add_argument(
        "--server",
        default=os.environ.get("LABD_SERVER"),
        help="fetch the keys from this lab, online (default: $LABD_SERVER; --key wins)",
    )
    p.add_argument(
        "--signature", type=Path, help="a record's signature (default: FILE.sig.json beside it)"
    )
    json_option(p)

    keys = commands.add_parser("keys", help="the operator's: the keys the lab signs with")
    actions = keys.add_subparsers(dest="action", required=True)
    rotate = actions.add_parser("rotate", help="sign with a new key from now on (old ones stay)")
    settings.add(rotate, [settings.get("data")])
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


def check(
    target: Path, keys: dict[str, Ed25519PublicKey], signature: Path | None = None
) -> dict[str, Any]:
    """Verify ``target`` (a record or an export); what was checked (``Mismatch`` if not)."""
    if target.is_dir():
        return _export(target, keys)
    return _record(target, keys, signature or target.with_name(target.name + SIGNATURE_SIDECAR))


def _signature(path: Path) -> Signature:
    try:
        data = json.loads(path.read_bytes())
    except (ValueError, UnicodeDecodeError) as err:
        raise ValueError(f"{path} is not a labd signature (it is not JSON: {err})") from None
    if not isinstance(data, dict):
        raise ValueError(f"{path} is not a labd signature (not a JSON object)")
    return Signature.from_json(data)


def _record(mcap: Path, keys: dict[str, Ed25519PublicKey], sidecar: Path) -> dict[str, Any]:
    if not sidecar.exists():
        raise ValueError(
            f"no signature for {mcap}: expected {sidecar} (`labd download` writes it; a"
            " record is signed when a lab files it, never by labd run)"
        )
    signed = _signature(sidecar)
    verify(signed, keys)
    statement = signed.statement
    if statement.get("schema") not in RECORDS:
        raise ValueError(f"{sidecar} signs {statement.get('schema')}, not a record")
    if not isinstance(statement.get("mcap"), str):
        raise Mismatch(
            f"the lab signed trial {statement.get('trial')} without a record (it ended"
            f" {statement.get('outcome') or statement.get('status')}): it vouches for no file"
        )
    changed = _bytes_changed(mcap, statement)
    try:
        facts = LabHost().read_record(mcap, statement.get("digest_topics") or [])
    except TrialError as err:
        changed.append(f"it can no longer be read as the record the lab signed ({err})")
    else:
        changed += record_differences(_claims(statement), facts)
        if len(changed) == 1 and changed[0].startswith("the file's bytes"):
            changed.append(
                "its manifest, its observations and actions and its outcome are as"
                " signed, so what changed is elsewhere: an attachment (a log, the model),"
                " a topic outside the data digest, or bytes added"
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


def _bytes_changed(mcap: Path, statement: dict[str, Any]) -> list[str]:
    """The file's sha256 and size against those signed (a /1 statement signed no size)."""
    digest, size = file_digest(mcap), mcap.stat().st_size
    signed_size = statement.get("mcap_size")
    if digest == statement["mcap"] and signed_size in (None, size):
        return []
    said = f"{statement['mcap']}" + (f", {signed_size:,} bytes" if signed_size else "")
    return [
        f"the file's bytes differ from what the lab signed ({digest}, {size:,} bytes; the"
        f" lab signed {said})"
    ]


def _claims(statement: dict[str, Any]) -> Claims:
    """What a record statement says the file holds. A trial's record says its outcome
    and metrics in ``outcome.json`` (a demonstration's says them in its own words)."""
    trial = statement.get("kind") == "trial"
    metrics = statement.get("metrics")
    return Claims(
        statement.get("manifest_digest"),
        statement.get("data_digest"),
        status=statement.get("status") if trial else None,
        outcome=statement.get("outcome") if trial else None,
        metrics=metrics if trial and isinstance(metrics, dict) else None,
    )


def _export(folder: Path, keys: dict[str, Ed25519PublicKey]) -> dict[str, Any]:
    path = folder / EXPORT_SIGNATURE
    if not path.exists():
        raise ValueError(f"{folder} holds no {EXPORT_SIGNATURE}: not a signed export")
    signed = _signature(path)
    verify(signed, keys)
    statement = signed.statement
    if statement.get("schema") != EXPORT:
        raise ValueError(f"{path} signs {statement.get('schema')}, not an export")
    signed_files = statement.get("files")
    if not isinstance(signed_files, dict):
        raise ValueError(f"{path} signs no list of files")
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
    trials = _trials(statement)
    which = (
        f"trial {trials[0]}" if "trial" in statement else f"trials {', '.join(map(str, trials))}"
    )
    return {
        "verified": True,
        "kind": "export",
        "trial": trials[0] if "trial" in statement else None,
        "trials": trials,
        "key": signed.key,
        "summary": (
            f"{folder}: verified: the {statement.get('format')} export of {which},"
            f" {len(signed_files)} files, signed by {signed.key}"
        ),
    }


def _trials(statement: dict[str, Any]) -> list[Any]:
    """The trials an export statement names: ``trial`` (one) or ``trials`` (many)."""
    if "trial" in statement:
        return [statement["trial"]]
    listed = statement.get("trials")
    if not isinstance(listed, list):
        return []
    return [t.get("trial") for t in listed if isinstance(t, dict)]


def _keys(args: argparse.Namespace) -> dict[str, Ed25519PublicKey]:
    if args.key is not None:
        return load_keys(args.key.read_bytes(), str(args.key))
    if args.server:
        with ApiClient(args.server) as client:
            answer = client.request("GET", "/api/keys")
        return load_keys(answer.content, mask_url(f"{args.server}/api/keys"))
    raise ValueError(
        "give the lab's keys: --key FILE (from its /api/keys), or --server URL (or $LABD_SERVER)"
    )


def _rotate(args: argparse.Namespace) -> int:
    keyring = Keyring((args.data / "keys").resolve())
    old = keyring.current
    new = keyring.rotate()
    text = f"the lab signs with {new} from now on; {old} still verifies what it signed"
    emit(args, {"current": new, "previous": old}, lambda: [text])
    return 0
