"""``labd run``: the local pre-flight. One trial, no server.

    labd run PATH|URL [--ref REF] [--task TASK] [--seed N] [--param NAME=VALUE ...]
             [--sandbox docker|bwrap] [--out DIR] [--data DIR] [--server URL] [--json]

A repository whose lab.toml has ``[data]`` learns from archived records: they are
resolved and pinned as a lab pins them at submit time, against a lab's archive
(``--server URL``: its public API) or the local one under ``--data`` (the folder
``labd serve --data`` keeps), and mounted read-only at ``LAB_DATA_DIR``.

It runs the same trial a lab would (the same sandbox, the same recording), prints the
outcome, the manifest digest and the data digest, and exits 0 only when the task was
achieved (``success``); 1 for ``fail``, 3 for ``error``, 2 for a usage error
(``labd.commands.common``).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import secrets
import time
from pathlib import Path
from typing import Any

import sandbox
from labd.commands.common import exit_code, fail, json_option, param_option
from labd.config import DATA
from labd.errors import LabError
from labd.trial import LabHost, client_library
from repository.blobs import BlobStore
from repository.index import Filters, Index
from repository.trial import Order, Trial
from sandbox.api import Limits, SandboxError
from scheduler.client import ApiClient
from scheduler.data import Archive, LocalArchive, RemoteArchive
from scheduler.errors import InvalidRequest
from scheduler.runner import RunOptions, TrialResult, run_trial


def add_parser(commands: Any) -> None:
    run = commands.add_parser("run", help="run a controller repository as one trial, locally")
    run.add_argument("source", metavar="PATH|URL", help="the controller's folder or git URL")
    run.add_argument("--ref", help="branch, tag or commit (default: the folder as it is / HEAD)")
    run.add_argument("--task", help="the task (default: the one lab.toml names)")
    run.add_argument("--seed", type=int, default=0, help="the episode's seed (default: 0)")
    param_option(run)
    run.add_argument(
        "--sandbox",
        choices=["docker", "bwrap"],
        help="isolation backend (default: docker if an engine answers, else bwrap)",
    )
    run.add_argument("--out", type=Path, help="the trial's folder (default: DATA/runs/...)")
    run.add_argument(
        "--data",
        type=Path,
        default=DATA,
        help="where runs and caches are kept (default: %(default)s)",
    )
    run.add_argument(
        "--wall",
        type=float,
        default=Limits().wall,
        help="seconds the controller may run (default: %(default)g)",
    )
    run.add_argument(
        "--server",
        metavar="URL",
        help="resolve lab.toml's [data] against this lab's archive (default: the one in --data)",
    )
    json_option(run)


def main(args: argparse.Namespace) -> int:
    params = dict(args.param)
    try:
        backend = sandbox.backend(
            args.sandbox, args.data / "cache", extra_packages=[client_library()]
        )
    except (LabError, SandboxError) as err:
        return fail(args, str(err))
    out = (
        args.out or args.data / "runs" / f"{time.strftime('%Y%m%d-%H%M%S')}-{secrets.token_hex(3)}"
    )
    order = Order(
        repository=args.source, ref=args.ref, task=args.task, params=params, seed=args.seed
    )
    options = RunOptions(limits=Limits(wall=args.wall))
    with contextlib.ExitStack() as stack:
        resolver = _archive(args, stack)
        try:
            result = asyncio.run(
                run_trial(
                    order,
                    backend=backend,
                    host=LabHost(),
                    out=out,
                    cache=args.data / "cache",
                    options=options,
                    resolver=resolver,
                )
            )
        except InvalidRequest as err:  # a task or parameter that is not there: a usage error
            return fail(args, str(err))
    if args.json:
        print(json.dumps(result.to_json(), indent=2))
    else:
        report(result)
    return int(exit_code(result.status, result.outcome))


def _archive(args: argparse.Namespace, stack: contextlib.ExitStack) -> Archive | None:
    """Where [data] is resolved: a lab's API, or the archive under --data if it has one
    (opened only if the repository asks for data)."""
    if args.server:
        client: ApiClient = stack.enter_context(ApiClient(args.server))
        return RemoteArchive(client)
    index_file = args.data / "index.sqlite"
    if not index_file.is_file():
        return None
    local = _LocalArchive(index_file, args.data / "blobs")
    stack.callback(local.close)
    return local


class _LocalArchive:
    """The archive of a lab's data folder, opened when first asked."""

    def __init__(self, index_file: Path, blobs: Path) -> None:
        self.index_file = index_file
        self.blobs = blobs
        self.opened: LocalArchive | None = None

    def _open(self) -> LocalArchive:
        if self.opened is None:
            index = Index.open(f"sqlite:///{self.index_file.resolve()}")
            self.opened = LocalArchive(index, BlobStore(str(self.blobs.resolve())))
        return self.opened

    def trial(self, trial_id: int) -> Trial:
        return self._open().trial(trial_id)

    def find(self, filters: Filters, limit: int) -> list[Trial]:
        return self._open().find(filters, limit)

    def copy_to(self, digest: str, dest: str | Path) -> Path:
        return self._open().copy_to(digest, dest)

    def close(self) -> None:
        if self.opened is not None:
            self.opened.index.close()


def report(result: TrialResult) -> None:
    what = result.outcome.value.upper() if result.outcome else result.status.value
    print(f"trial {what}: {result.reason}")
    manifest = result.manifest
    if manifest is not None:
        print(
            f"  task {manifest.task.name}, seed {manifest.seed}, sandbox {result.backend}, "
            f"{result.wall_seconds:.1f} s"
        )
    if result.metrics:
        shown = ", ".join(f"{k}={_fmt(v)}" for k, v in result.metrics.items())
        print(f"  metrics: {shown}")
    if result.manifest_digest:
        print(f"  manifest sha256:{result.manifest_digest}")
    if result.data_digest:
        print(f"  data     sha256:{result.data_digest}")
    pinned = manifest.data if manifest is not None else ()
    if pinned:
        trials = ", ".join(str(p.trial) for p in pinned)
        print(f"  learnt from {len(pinned)} pinned records: trials {trials}")
    if result.mcap:
        print(f"  record   {result.mcap}")
    print(f"  folder   {result.folder}")


def _fmt(value: Any) -> str:
    return f"{value:.4g}" if isinstance(value, float) else str(value)
