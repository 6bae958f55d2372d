"""Records an older lab filed still verify, read and replay with today's code.

``tests/data/records`` holds real records (a maze trial, a dm_control trial, a held-out
episode run blind, a drive of the live maze robot), each with the signature its lab
made and that lab's public keys; ``make.py`` there made them by running ``labd serve``
from an older commit (``index.json`` names it). Filed records are never rewritten, so
the code that reads them must keep reading them as they are: their signatures check,
their manifests are read (``Manifest.from_json``) and written again with the digest
that was filed, and their replays are identical.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from labd.recorder.record import read_manifest
from labd.replay import replay
from repository.digests import manifest_digest
from repository.manifest import Manifest
from repository.trial import Kind

GOLDEN = Path(__file__).resolve().parents[1] / "data" / "records"
INDEX: dict[str, dict[str, Any]] = json.loads((GOLDEN / "index.json").read_text())
NAMES = sorted(INDEX)
pytestmark = pytest.mark.timeout(120)


def test_the_set_has_each_kind():
    manifests = [Manifest.from_json(read_manifest(GOLDEN / f"{n}.mcap") or {}) for n in NAMES]
    assert {m.kind for m in manifests} == {Kind.TRIAL, Kind.DEMONSTRATION}
    assert any(m.blind for m in manifests)
    assert {m.task.name for m in manifests} >= {"icreate-maze", "dmc-cartpole-balance"}


@pytest.mark.parametrize("name", NAMES)
def test_an_old_record_verifies_with_its_signature(name):
    """``labd verify``, as a user runs it on what ``labd download`` gave them."""
    done = subprocess.run(
        [sys.executable, "-m", "labd", "verify", str(GOLDEN / f"{name}.mcap"), "--key",
         str(GOLDEN / "lab-keys.json")],
        capture_output=True, text=True, timeout=100, check=False,
    )  # fmt: skip
    assert done.returncode == 0, done.stdout + done.stderr
    assert "verified: trial" in done.stdout


@pytest.mark.parametrize("name", NAMES)
def test_an_old_record_s_manifest_is_read_and_written_with_its_filed_digest(name):
    held = read_manifest(GOLDEN / f"{name}.mcap")
    assert held is not None
    manifest = Manifest.from_json(held)
    assert manifest.to_json() == held
    assert manifest.digest == manifest_digest(held) == INDEX[name]["manifest_digest"]
    signed = json.loads((GOLDEN / f"{name}.mcap.sig.json").read_text())
    assert signed["statement"]["manifest_digest"] == manifest.digest


@pytest.mark.parametrize("name", NAMES)
def test_an_old_record_replays_identically(name):
    verdict = replay(GOLDEN / f"{name}.mcap")
    assert verdict.verified, str(verdict)
    assert verdict.ticks > 10
