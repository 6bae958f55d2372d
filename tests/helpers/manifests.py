"""Manifests as the lab writes them, for records a test makes itself (``Manifest.trial``):
what a replay, an export or a summary reads of a record is a whole manifest, never a few
of its keys."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from repository.manifest import Code, Controller, Manifest, TaskVersion, Versions
from repository.trial import Value

TREE = "sha256:" + "0" * 64


def trial_manifest(
    task: str,
    version: str,
    parameters: Mapping[str, Value],
    seed: int,
    *,
    model_sha256: str,
    realtime: bool = False,
    repository: str = "tests/in-process",
    commit: str | None = None,
) -> Manifest:
    """A trial's manifest for a robot stepped in the test's own process, in lockstep
    (``realtime``: on the wall clock); its code named by ``repository`` and ``commit``."""
    return Manifest.trial(
        code=Code(repository, commit, TREE, None, "", dirty=False),
        controller=Controller(("python", "controller.py"), realtime, None, None),
        task=TaskVersion(task, version),
        parameters=parameters,
        seed=seed,
        runtime="in-process",
        versions=Versions.here(),
        model_sha256=model_sha256,
    )


def of_robot(robot: Any, seed: int, **options: Any) -> dict[str, Any]:
    """The manifest of a ``labd.sim.robot.Robot`` the test steps, as a record holds it."""
    spec = robot.sim.spec
    made = trial_manifest(
        spec.name,
        spec.version,
        robot.values,
        seed,
        model_sha256=robot.sim.model_digest(),
        **options,
    )
    return made.to_json()
