"""Every kind of manifest the lab has written, held to the bytes and digests records hold.

``tests/data/manifests`` keeps real manifests of every kind (README.md there says where each
came from): trials with and without pinned data, interfaces, requirements and node
packages, held-out episodes run blind, dirty work trees, realtime controllers, live and
scripted drives, and ones older code wrote. A record filed is never rewritten, and its
manifest digest names its experiment and is what the lab signed: today's writers must
give these very bytes.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from repository.digests import manifest_digest, readable_json
from repository.trial import Kind, Outcome, PinnedRecord
from scheduler import manifest as writer
from scheduler.source import Source

GOLDEN = Path(__file__).resolve().parents[1] / "data" / "manifests"
INDEX: dict[str, dict[str, Any]] = json.loads((GOLDEN / "index.json").read_text())
NAMES = sorted(INDEX)
TRIALS = [name for name in NAMES if name.startswith("trial-")]


def stored(name: str) -> bytes:
    return (GOLDEN / f"{name}.json").read_bytes()


def loaded(name: str) -> dict[str, Any]:
    value: dict[str, Any] = json.loads(stored(name))
    return value


def keys(manifest: dict[str, Any], prefix: str = "") -> list[str]:
    """Its keys in the order they were written, nested ones dotted (parameters whole)."""
    found = []
    for key, value in manifest.items():
        found.append(prefix + key)
        if isinstance(value, dict) and key != "parameters":
            found += keys(value, f"{prefix}{key}.")
    return found


def test_every_kind_is_in_the_set():
    """The set has each optional part of a manifest at least once, and both kinds."""
    manifests = [loaded(name) for name in NAMES]
    trials = [m for m in manifests if "robot" not in m]
    drives = [m for m in manifests if "robot" in m]
    assert len(trials) >= 10 and len(drives) >= 5
    controller = [key for m in trials for key in m["controller"]]
    for key in ("interfaces", "interfaces_sha256", "node_packages_sha256"):
        assert key in controller
    assert any(m["controller"]["requirements"] for m in trials)
    assert any(m["controller"]["realtime"] for m in trials)
    assert any("data" in m for m in trials) and any(m.get("blind") is True for m in trials)
    assert any(m["dirty"] for m in trials) and any(m["commit"] is None for m in trials)
    assert any(m["subdir"] for m in trials)
    assert any("claimed_user" in m["driver"] for m in drives)
    assert {m["task"]["name"] for m in manifests} >= {
        "icreate-maze",
        "pr2-table",
        "dmc-cartpole-balance",
    }
    assert any(not name.isascii() for m in manifests for name in json.dumps(m, ensure_ascii=False))


@pytest.mark.parametrize("name", NAMES)
def test_a_stored_manifest_is_a_records_attachment_with_its_filed_digest(name):
    """The file is the record's manifest attachment byte for byte; its digest is the one
    filed; its writing order, where known, names every key once."""
    manifest = loaded(name)
    assert readable_json(manifest) == stored(name)
    assert manifest_digest(manifest) == INDEX[name]["digest"]
    order = INDEX[name]["keys"]
    if order is not None:
        assert sorted(order) == sorted(keys(manifest))


@pytest.mark.parametrize("name", TRIALS)
def test_todays_trial_writer_writes_each_trial_manifest(name, monkeypatch):
    """``scheduler.manifest.build``, given what a stored trial manifest says ran, writes it
    again: the same bytes, the same digest, its keys in the same order."""
    manifest = loaded(name)
    order = [key.split(".")[1] for key in INDEX[name]["keys"] if key.startswith("versions.")]
    monkeypatch.setattr(writer, "versions", lambda: {k: manifest["versions"][k] for k in order})
    controller = manifest["controller"]

    class Config:  # what build reads of a ControllerConfig
        command = tuple(controller["command"])
        realtime = controller["realtime"]
        requirements = controller["requirements"]
        interfaces = tuple(controller.get("interfaces", ()))
        interfaces_sha256 = controller.get("interfaces_sha256")

    data = [
        PinnedRecord(
            trial=entry["trial"],
            kind=Kind.DEMONSTRATION,
            task=manifest["task"]["name"],
            seed=0,
            outcome=Outcome.SUCCESS,
            data_digest=entry["data_digest"],
            digest_topics=[],
            mcap=entry["mcap"],
            size=0,
        )
        for entry in manifest.get("data", ())
    ]
    again = writer.build(
        source=Source(
            manifest["repository"],
            manifest["commit"],
            manifest["tree"],
            manifest["git_tree"],
            manifest["subdir"],
            manifest["dirty"],
        ),
        controller=Config(),  # type: ignore[arg-type]
        task=manifest["task"]["name"],
        task_version=manifest["task"]["version"],
        parameters=manifest["parameters"],
        seed=manifest["seed"],
        runtime=manifest["runtime"],
        requirements_sha256=controller["requirements_sha256"],
        model_sha256=manifest["model_sha256"],
        data=data,
        node_packages_sha256=controller.get("node_packages_sha256"),
        blind=manifest.get("blind", False),
    )
    assert readable_json(again) == stored(name)
    assert manifest_digest(again) == INDEX[name]["digest"]
    assert keys(again) == INDEX[name]["keys"]
