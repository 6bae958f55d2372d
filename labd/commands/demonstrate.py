"""``labd demonstrate``: scripted demonstrations of the maze, filed in a lab's archive.

    labd demonstrate [--seeds N ...] [--count N] [--user NAME] [--data DIR | --database URL]

For when no person is at hand to drive the robot from its page: a driver that knows the
maze (``labd.scripted``) drives a live icreate-maze robot to the goal, once per seed
(or ``--count`` times on the seeds that follow one another), and each drive is recorded
and filed, signed, as a ``demonstration`` by ``--user``, exactly as a person's drive
from ``/robots/icreate-1`` would be. Like ``labd users``, it writes to the lab's archive
directly (the operator's command, run where the lab keeps its data; a running ``labd
serve`` sees the demonstrations at once).
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path
from typing import Any

from labd.commands import settings
from labd.commands.common import fail, json_option
from labd.graph.types import TypeRegistry
from labd.live import Driving
from labd.scripted import demonstrate
from labd.service import Service, ServiceConfig
from labd.station import Station

TASK = "icreate-maze"


def add_parser(commands: Any) -> None:
    p = commands.add_parser(
        "demonstrate", help="scripted maze demonstrations, filed in the lab's archive"
    )
    p.add_argument("--seeds", type=int, nargs="+", metavar="N", help="the mazes to drive")
    p.add_argument(
        "--count", type=int, default=5, help="without --seeds: how many (default: %(default)s)"
    )
    p.add_argument(
        "--user",
        default="script",
        help="who the demonstrations are filed under (default: %(default)s)",
    )
    settings.add(p, [settings.get("data"), settings.get("database")])
    json_option(p)


def main(args: argparse.Namespace) -> int:
    seeds: list[int | None] = list(args.seeds or [None] * args.count)
    if not seeds or args.count < 1:
        return fail(args, "give --seeds, or a --count of at least 1")
    service = Service(ServiceConfig(data=args.data, database=args.database, workers=0))
    station = Station(
        TypeRegistry.default(), "icreate-script", TASK, {}, 0, live=True, protected_prefixes=()
    )
    filed: list[dict[str, Any]] = []

    def file(demo: Any) -> None:
        trial = service.file_demonstration(demo)
        filed.append({"trial": trial, "seed": demo.seed, "achieved": demo.achieved})
        if not args.json:
            print(f"demonstration {trial}: seed {demo.seed}: {demo.reason}", flush=True)

    with tempfile.TemporaryDirectory(prefix="labd-demonstrate-") as work:
        driving = Driving(station, work=Path(work), file=file)
        try:
            for seed in seeds:
                demonstrate(station, driving, user=args.user, seed=seed)
        finally:
            driving.close()
            station.close()
            service.index.close()
    if args.json:
        print(json.dumps({"demonstrations": filed}))
    return 0
