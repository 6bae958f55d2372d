"""``labd export``: trials as data for learning, made by a lab and downloaded.

    labd export TRIAL --format lerobot|parquet [-o DIR]     (the formats of repository.formats)
    labd export --task T [--kind K --outcome O --user U --limit N] [--trials ID ...] --format F

The lab makes the export (``repository.export``) and keeps it beside the record; this
downloads it and reads it back to count its frames and episodes. That reading is the
formats' own (``repository.formats``: Parquet through pyarrow), which is why the command
is a module of its own: the other commands that talk to a lab
(``labd.commands.remote``) start without it.

It takes ``--server URL`` and ``--json`` as they do; exit codes are in
``labd.commands.common``.
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
import zipfile
from pathlib import Path
from typing import Any
from urllib.parse import urlencode

from labd.commands.common import ExitCode, emit, fail, server_options
from repository.digests import readable_json
from repository.errors import ArchiveError
from repository.formats import FORMATS
from repository.trial import Kind, Outcome
from repository.well_known import EXPORT_SIGNATURE
from scheduler.client import ApiClient
from scheduler.errors import RemoteError


def add_parser(commands: Any) -> None:
    p = commands.add_parser(
        "export", help="export trials for learning: a row per control tick, every camera"
    )
    p.add_argument("trial", type=int, nargs="?", metavar="TRIAL", help="one trial's number")
    p.add_argument("--format", required=True, choices=sorted(FORMATS), help="the format")
    p.add_argument("-o", "--output", type=Path, help="the folder (default: trial-N-FORMAT)")
    many = p.add_argument_group("many trials as one dataset, one episode each (as [data])")
    many.add_argument("--trials", type=int, nargs="+", default=[], metavar="ID", help="by id")
    many.add_argument("--task", help="the query: trials of this task")
    many.add_argument("--kind", choices=[k.value for k in Kind], help="... of this kind")
    many.add_argument("--outcome", choices=[o.value for o in Outcome], help="... that ended so")
    many.add_argument("--user", help="... submitted (or driven) by this user")
    many.add_argument("--limit", type=int, help="... the newest this many")
    server_options(p)


def main(args: argparse.Namespace) -> int:
    try:
        with ApiClient(args.server, getattr(args, "token", None)) as client:
            return _export(client, args)
    except (RemoteError, ArchiveError) as err:
        return fail(args, str(err))


def _export(client: ApiClient, args: argparse.Namespace) -> int:
    """The lab makes the export (once; it keeps it beside the record); this downloads it."""
    query = {k: getattr(args, k) for k in ("task", "kind", "outcome", "user", "limit")}
    if args.trials or any(v is not None for v in query.values()):
        return _export_many(client, args, query)
    if args.trial is None:
        return fail(args, "name a TRIAL, or trials to export together (--trials, --task ...)")
    fmt = FORMATS[args.format]
    out = args.output or Path(f"trial-{args.trial}-{fmt.name}")
    if _taken(out):
        return fail(args, f"{out} already exists: give a new or empty folder (-o)")
    path = f"/api/trials/{args.trial}/export/{fmt.name}"
    size = _download(client, path, out, into=fmt.served)
    if fmt.served is not None:  # the export's one file; its signature is served beside it
        signature = client.request("GET", f"{path}/signature").json()
        (out / EXPORT_SIGNATURE).write_bytes(readable_json(signature))
    frames = fmt.frames(out)
    info = {"path": str(out), "format": args.format, "frames": frames, "bytes": size}
    emit(args, info, lambda: [f"{out}: {frames} frames ({args.format}, {size:,} bytes)"])
    return ExitCode.SUCCESS


def _export_many(client: ApiClient, args: argparse.Namespace, query: dict[str, Any]) -> int:
    """Many trials as one dataset: the lab chooses them as lab.toml's [data] does."""
    ids = ([args.trial] if args.trial is not None else []) + list(args.trials)
    params: list[tuple[str, str | int]] = [("trials", i) for i in ids]
    params += [(k, v) for k, v in query.items() if v is not None]
    fmt = FORMATS[args.format]
    out = args.output or Path(f"export-{fmt.name}")
    if _taken(out):
        return fail(args, f"{out} already exists: give a new or empty folder (-o)")
    size = _download(client, f"/api/exports/{fmt.name}?" + urlencode(params), out)
    frames = fmt.frames(out)
    episodes = fmt.episodes(out)
    info = {
        "path": str(out),
        "format": args.format,
        "frames": frames,
        "episodes": episodes,
        "bytes": size,
    }
    emit(
        args,
        info,
        lambda: [f"{out}: {episodes} episodes, {frames} frames ({args.format}, {size:,} bytes)"],
    )
    return ExitCode.SUCCESS


def _taken(out: Path) -> bool:
    """Whether ``out`` is a file or a folder with something in it."""
    return out.exists() and (not out.is_dir() or any(out.iterdir()))


def _download(client: ApiClient, path: str, out: Path, *, into: str | None = None) -> int:
    """Download ``path`` into the folder ``out``: the one file named ``into``, or else a
    zip of a folder, unpacked there. Its size in bytes."""
    with tempfile.TemporaryDirectory(prefix="labd-export-") as folder:
        got = Path(folder) / "export"
        size = client.download(path, got)
        out.mkdir(parents=True, exist_ok=True)
        if into is not None:
            shutil.move(got, out / into)
        else:
            with zipfile.ZipFile(got) as archive:
                archive.extractall(out)
    return size
