"""``labd replay TRIAL|RECORD``: re-simulate a record from its actions, and render it.

    labd replay trial-12.mcap                       a downloaded record, no server
    labd replay 12 --server URL                      a trial of a lab (downloaded first)
    labd replay lab-data/runs/... --render camera --render scene --size 640x480 --fps 15

It rebuilds the task from the record's manifest (refusing another model or simulator),
applies the recorded commands tick by tick and compares every observation the robot
publishes with the record: "replay verified", or where it diverged and the two values.
``--render CAMERA`` writes an MP4 of that camera (``scene``: the whole scene from aside)
into ``-o DIR``, even if the controller never looked. Exit codes: 0 verified, 5
diverged, 2 for a record that cannot be replayed or a usage error.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path
from typing import Any

from labd.commands.common import ExitCode, emit, fail, server_options
from labd.errors import LabError
from labd.replay import replay
from labd.video import Video, VideoSpec
from scheduler.client import ApiClient
from scheduler.errors import RemoteError


def add_parser(commands: Any) -> None:
    p = commands.add_parser("replay", help="re-simulate a record and compare; render videos")
    p.add_argument("target", metavar="TRIAL|RECORD", help="a trial number, or an MCAP file")
    p.add_argument(
        "--render",
        action="append",
        default=[],
        metavar="CAMERA",
        help="write an MP4 of this camera, or of 'scene' (repeatable; default: none)",
    )
    p.add_argument(
        "--size", default="320x240", help="the videos' WIDTHxHEIGHT (default: %(default)s)"
    )
    p.add_argument(
        "--fps", type=float, default=10.0, help="the videos' frame rate (default: %(default)g)"
    )
    p.add_argument(
        "-o",
        "--output",
        type=Path,
        help="where videos go (default: replay-TRIAL or RECORD's folder)",
    )
    server_options(p)


def main(args: argparse.Namespace) -> int:
    try:
        with tempfile.TemporaryDirectory(prefix="labd-replay-") as folder:
            record, name = _record(args, Path(folder))
            return _replay(args, record, name)
    except (LabError, RemoteError, OSError, ValueError) as err:
        return fail(args, str(err))


def _record(args: argparse.Namespace, folder: Path) -> tuple[Path, str]:
    target = Path(args.target)
    if target.exists():
        return target, target.stem
    if not args.target.isdigit():
        raise ValueError(f"{args.target}: no such file, and not a trial number")
    record = folder / f"trial-{args.target}.mcap"
    with ApiClient(args.server) as client:
        client.download(f"/api/trials/{args.target}/data.mcap", record)
    return record, f"trial-{args.target}"


def _replay(args: argparse.Namespace, record: Path, name: str) -> int:
    out = args.output or (
        Path(f"replay-{name}") if not Path(args.target).exists() else record.parent
    )
    videos = [
        Video(VideoSpec.parse(camera, args.size, args.fps), out / f"{name}-{camera}.mp4")
        for camera in args.render
    ]
    try:
        verdict = replay(record, renderers=videos)
    finally:
        for video in videos:
            video.close()
    made = {v.spec.camera: str(v.out) for v in videos if v.frames}
    data = {**verdict.to_json(), "videos": made}
    lines = [str(verdict)] + [f"  {camera}: {path}" for camera, path in made.items()]
    emit(args, data, lambda: lines)
    return int(ExitCode.SUCCESS if verdict.verified else ExitCode.DIVERGED)
