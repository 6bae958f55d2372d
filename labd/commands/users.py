"""``labd users add NAME``: make a user of the lab and print their token.

It writes to the lab's database directly (the operator's command, run where the lab
runs), so it takes ``--data`` or ``--database`` as ``labd serve`` does. Only the
token's hash is kept: the token is printed once.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from labd.commands.common import fail, json_option
from labd.config import DATA
from labd.service import ServiceConfig
from repository.errors import ArchiveError
from repository.index import Index, UserLimits

USER = UserLimits()


def add_parser(commands: Any) -> None:
    users = commands.add_parser("users", help="the lab's users and their tokens")
    actions = users.add_subparsers(dest="action", required=True)
    add = actions.add_parser("add", help="add a user and print their token")
    add.add_argument("name", help="letters, digits, '-', '_' or '.'")
    add.add_argument(
        "--data",
        type=Path,
        default=DATA,
        help="the lab's data folder (default: %(default)s)",
    )
    add.add_argument("--database", help="SQLAlchemy URL (default: sqlite:///DATA/index.sqlite)")
    add.add_argument(
        "--max-running",
        type=int,
        default=USER.max_running,
        help="trials running at once (default: %(default)s)",
    )
    add.add_argument(
        "--max-daily",
        type=int,
        default=USER.max_daily,
        help="trials submitted per 24 h (default: %(default)s)",
    )
    add.add_argument(
        "--worker", action="store_true", help="a worker's token: labd worker --server uses it"
    )
    json_option(add)


def main(args: argparse.Namespace) -> int:
    config = ServiceConfig(data=args.data, database=args.database)
    args.data.mkdir(parents=True, exist_ok=True)
    try:
        index = Index.open(config.database_url)
        try:
            token = index.add_user(
                args.name,
                max_running=args.max_running,
                max_daily=args.max_daily,
                worker=args.worker,
            )
        finally:
            index.close()
    except ArchiveError as err:
        return fail(args, str(err))
    if args.json:
        print(json.dumps({"name": args.name, "token": token}))
    else:
        print(token)
        print(f"(user {args.name}; the lab keeps only a hash: save this token)", file=sys.stderr)
    return 0
