"""Canonical JSON, and the manifest digest computed over it: one way, for every part.

A digest is worth only the bytes it is computed over, and the lab's are recomputed far
from where they were made: the recorder writes a manifest into a record, the scheduler
and the filing check recompute its digest, the lab signs statements that name it, and
``labd verify`` checks a signature offline years later. So a value is written for
hashing or signing one way, here: keys sorted, no spaces, UTF-8 kept as it is
(``ensure_ascii=False``), NaN and the infinities as Python's ``json`` writes them.
Values compared as JSON (``scheduler.filing``) are written the same way, so that NaN
equals NaN and key order is moot.

Records filed long ago must verify and replay: nothing here may ever change what a
digest is computed over. The one variant, ``ascii_only``, is there for that reason:
the digest of a repository's interface files was first computed with non-ASCII text
escaped, and stays so.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping
from typing import Any


def canonical_json(value: Any, *, ascii_only: bool = False) -> str:
    """``value`` as canonical JSON text: sorted keys, no spaces, UTF-8 kept (``ascii_only``:
    non-ASCII escaped as ``\\uXXXX``, for the digests first computed so)."""
    return json.dumps(value, sort_keys=True, separators=(",", ":"), ensure_ascii=ascii_only)


def sha256_json(value: Any, *, ascii_only: bool = False) -> str:
    """The sha256 (hex) of ``value``'s canonical JSON, encoded as UTF-8."""
    return hashlib.sha256(canonical_json(value, ascii_only=ascii_only).encode()).hexdigest()


def manifest_digest(manifest: Mapping[str, Any]) -> str:
    """The digest that names an experiment: the sha256 (hex) of its manifest's canonical
    JSON, as the record holds it (``labd.recorder``)."""
    return sha256_json(manifest)


def readable_json(value: Any) -> bytes:
    """``value`` as JSON for people, as the files the lab writes hold it (a record's
    manifest and outcome attachments, a signature beside its file): indented, keys
    sorted, a final newline; anything JSON has no form for as its ``str``, so a record
    is never lost to one odd value. These bytes are hashed too (an attachment is part of
    the record's file, which the lab signs), so they are written one way as well."""
    return (json.dumps(value, indent=2, sort_keys=True, default=str) + "\n").encode()
