"""The manifest of a trial: everything that decides what happened, and its digest.

The digest of the manifest names the experiment: the same repository and commit,
task and version, parameters, seed, controller runtime and model give the same
digest, and a rerun of a manifest is expected to give the same data.
"""

from __future__ import annotations

import functools
import platform
from collections.abc import Mapping, Sequence
from importlib import metadata
from typing import Any

from repository.trial import PinnedRecord
from scheduler.controller import ControllerConfig
from scheduler.source import Source

SCHEMA = "labd.trial/1"


def build(
    *,
    source: Source,
    controller: ControllerConfig,
    task: str,
    task_version: str,
    parameters: Mapping[str, Any],
    seed: int,
    runtime: str,
    requirements_sha256: str | None,
    model_sha256: str,
    data: Sequence[PinnedRecord] = (),
    node_packages_sha256: str | None = None,
    blind: bool = False,
) -> dict[str, Any]:
    manifest: dict[str, Any] = {
        "schema": SCHEMA,
        "repository": source.repository,
        "commit": source.commit,
        "tree": source.tree,
        "git_tree": source.git_tree,
        "subdir": source.subdir,
        "dirty": source.dirty,
        "task": {"name": task, "version": task_version},
        "parameters": dict(sorted(parameters.items())),
        "seed": seed,
        "controller": {
            "command": list(controller.command),
            "realtime": controller.realtime,
            "requirements": controller.requirements,
            "requirements_sha256": requirements_sha256,
        },
        "runtime": runtime,
        "versions": versions(),
        "model_sha256": model_sha256,
    }
    if controller.interfaces:  # only then, so manifests without keep their digests
        manifest["controller"]["interfaces"] = list(controller.interfaces)
        manifest["controller"]["interfaces_sha256"] = controller.interfaces_sha256
    if node_packages_sha256 is not None:  # only then, likewise
        manifest["controller"]["node_packages_sha256"] = node_packages_sha256
    if data:  # the records it learns from; without, earlier manifests keep their digests
        manifest["data"] = [record.manifest_entry() for record in data]
    if blind:  # a held-out episode: the controller was told no seed (likewise, only then)
        manifest["blind"] = True
    return manifest


def versions() -> dict[str, str]:
    """The versions a manifest records (a new dict each call, for the caller to keep)."""
    return dict(_versions())


@functools.cache
def _versions() -> dict[str, str]:
    # Read once per process: looking packages up in their metadata took 10 ms a trial.
    return {
        "labd": _version("labd"),
        "mujoco": _version("mujoco"),
        "dm_control": _version("dm-control"),
        "python": platform.python_version(),
    }


def _version(package: str) -> str:
    try:
        return metadata.version(package)
    except metadata.PackageNotFoundError:
        return "unknown"
