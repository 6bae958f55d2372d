"""Every kind of manifest the lab has written, held to the bytes and digests records hold.

``tests/data/manifests`` keeps real manifests of every kind (README.md there says where each
came from): trials with and without pinned data, interfaces, requirements and node
packages, held-out episodes run blind, dirty work trees, realtime controllers, live and
scripted drives, and ones older code wrote. A record filed is never rewritten, and its
manifest digest names its experiment and is what the lab signed: ``Manifest`` must read
every one of them and write these very bytes again.
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import pytest

from repository.digests import canonical_json, manifest_digest, readable_json
from repository.errors import ManifestError
from repository.manifest import Driver, Manifest, TaskVersion
from repository.trial import Kind, Outcome, PinnedRecord

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
    legs = [m for m in manifests if m.get("kind") == "match"]
    trials = [m for m in manifests if "robot" not in m and m not in legs]
    drives = [m for m in manifests if "robot" in m]
    assert len(trials) >= 10 and len(drives) >= 5 and legs
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


@pytest.mark.parametrize("name", NAMES)
def test_a_stored_manifest_is_read_and_written_again_byte_for_byte(name):
    """``Manifest.from_json`` reads it and ``to_json`` writes it again: the record's bytes,
    its filed digest, its keys in the order its writer put them."""
    manifest = Manifest.from_json(loaded(name))
    written = manifest.to_json()
    assert readable_json(written) == stored(name)
    assert canonical_json(written) == canonical_json(loaded(name))
    assert manifest_digest(written) == manifest.digest == INDEX[name]["digest"]
    order = INDEX[name]["keys"]
    assert keys(written) == (order if order is not None else _writers_order(written))


def _writers_order(manifest: dict[str, Any]) -> list[str]:
    """The order today's writer puts a manifest's keys in, for the files whose writing
    order was not kept: that of another stored manifest of its kind with the same keys."""
    same = [
        INDEX[other]["keys"]
        for other in NAMES
        if INDEX[other]["keys"] is not None
        and sorted(INDEX[other]["keys"]) == sorted(keys(manifest))
    ]
    assert same, "no stored manifest of its kind has its keys"
    return list(same[0])


@pytest.mark.parametrize("name", NAMES)
def test_the_lab_s_constructors_write_each_stored_manifest(name):
    """``Manifest.trial``, ``Manifest.match`` and ``Manifest.drive``, given the parts a stored manifest says
    ran, write it again, byte for byte and key for key: what the runner and a live robot
    write is what records hold."""
    read = Manifest.from_json(loaded(name))
    task, params, versions = read.task, dict(read.parameters), read.versions
    if read.kind is Kind.TRIAL:
        assert read.code is not None and read.controller is not None and read.runtime
        made = Manifest.trial(
            code=read.code,
            controller=read.controller,
            task=task,
            parameters=dict(reversed(params.items())),  # the constructor sorts them
            seed=read.seed,
            runtime=read.runtime,
            versions=versions,
            model_sha256=read.model_sha256,
            data=[_pinned(p.trial, p.data_digest, p.mcap) for p in read.data],
            blind=read.blind,
        )
    elif read.kind is Kind.MATCH:
        assert read.runtime is not None
        made = Manifest.match(
            teams=read.teams,
            task=task,
            parameters=dict(reversed(params.items())),
            seed=read.seed,
            runtime=read.runtime,
            versions=versions,
            model_sha256=read.model_sha256,
        )
    else:
        assert read.robot is not None and read.driver is not None
        made = Manifest.drive(
            robot=read.robot,
            task=task,
            parameters=dict(reversed(params.items())),
            seed=read.seed,
            driver=read.driver,
            versions=versions,
            model_sha256=read.model_sha256,
        )
    assert made == read
    assert readable_json(made.to_json()) == stored(name)
    assert made.digest == INDEX[name]["digest"]
    assert keys(made.to_json()) == keys(read.to_json())


def _pinned(trial: int, data_digest: str, mcap: str) -> PinnedRecord:
    return PinnedRecord(
        trial=trial,
        kind=Kind.DEMONSTRATION,
        task="icreate-maze",
        seed=0,
        outcome=Outcome.SUCCESS,
        data_digest=data_digest,
        digest_topics=[],
        mcap=mcap,
        size=0,
    )


def test_what_readers_ask_is_an_attribute():
    """A trial's and a drive's manifests answer the same questions by attribute."""
    trial = Manifest.from_json(loaded("trial-everything-blind"))
    assert (trial.kind, trial.seed, trial.blind, trial.live, trial.realtime) == (
        Kind.TRIAL, 5, True, False, False
    )  # fmt: skip
    assert trial.repository is not None and trial.repository.endswith("/combo")
    assert trial.task == TaskVersion("icreate-maze", "1") and trial.parameters["maze_size"] == 5
    assert trial.controller is not None and trial.controller.interfaces == ("planner_msgs",)
    data = Manifest.from_json(loaded("trial-data"))
    assert [p.trial for p in data.data] and data.versions.mujoco
    drive = Manifest.from_json(loaded("drive-pr2-non-ascii"))
    assert (drive.kind, drive.live, drive.realtime, drive.repository, drive.commit) == (
        Kind.DEMONSTRATION, True, True, None, None
    )  # fmt: skip
    assert drive.driver == Driver("guest:page", "vidéo", "séance-1 ✓", claimed_user="Zoë")
    assert drive.robot == "pr2-1" and drive.task.name == "pr2-table"


def test_a_leg_s_manifest_names_both_teams_and_no_code_of_its_own():
    """A match leg's manifest has a team for each side and no code, controller or data
    of its own; one that names a single team, or keys it does not write, is refused."""
    leg = Manifest.from_json(loaded("match-leg-forfeit"))
    assert (leg.kind, leg.repository, leg.commit, leg.realtime, leg.live) == (
        Kind.MATCH, None, None, False, False
    )  # fmt: skip
    assert sorted(leg.teams) == ["away", "home"]
    assert leg.teams["home"].code.repository.endswith("soccer-chaser")
    assert leg.teams["away"].controller.command == ("python", "still.py")
    lone = loaded("match-leg-forfeit")
    del lone["teams"]["away"]
    with pytest.raises(ManifestError, match=r"manifest\.teams: must name two sides or more"):
        Manifest.from_json(lone)
    extra = loaded("match-leg-forfeit")
    extra["teams"]["home"]["data"] = []
    with pytest.raises(ManifestError, match=r"manifest\.teams\.home: 'data' is not a key"):
        Manifest.from_json(extra)


def _without(manifest: dict[str, Any], dotted: str) -> dict[str, Any]:
    copy = json.loads(json.dumps(manifest))
    *path, last = dotted.split(".")
    inner = copy
    for key in path:
        inner = inner[key]
    del inner[last]
    return copy


@pytest.mark.parametrize(
    ("name", "dotted"),
    [
        ("trial-repository-root", "seed"),
        ("drive-scripted", "seed"),
        ("trial-example-subdir", "task.version"),
        ("trial-dmc", "controller.requirements"),
        ("drive-claimed-user", "driver.session"),
        ("trial-folder-js", "versions.mujoco"),
        ("trial-pr2", "schema"),
    ],
)
def test_a_missing_key_is_an_error_naming_it(name, dotted):
    """A key a record lacks is an error naming it, never a default (a missing seed is not
    seed 0)."""
    with pytest.raises(ManifestError, match=rf"^manifest\.{re.escape(dotted)}: missing$"):
        Manifest.from_json(_without(loaded(name), dotted))


@pytest.mark.parametrize(
    ("change", "said"),
    [
        ({"seed": "4"}, r"manifest\.seed: must be an integer, not '4'"),
        ({"seed": True}, r"manifest\.seed: must be an integer, not True"),
        ({"dirty": None}, r"manifest\.dirty: must be true or false, not null"),
        ({"blind": False}, r"manifest\.blind: is written only as true"),
        ({"data": []}, r"manifest\.data: is written only as a list of records"),
        ({"note": "x"}, r"manifest: 'note' is not a key the lab writes here"),
        ({"schema": "labd.trial/2"}, r"manifest\.schema: is 'labd\.trial/2'; this lab reads"),
        (
            {"kind": "trial"},
            r"manifest\.kind: is 'trial'; only a drive's and a match's say their kind",
        ),
        ({"parameters": {"x": [1]}}, r"manifest\.parameters\.x: must be a number"),
    ],
)
def test_a_key_the_lab_would_not_write_is_an_error(change, said):
    """A value of another type, or a key or form the lab never writes, is refused: read
    and written back, it would not keep its digest."""
    with pytest.raises(ManifestError, match=said):
        Manifest.from_json({**loaded("trial-repository-root"), **change})
