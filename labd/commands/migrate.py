"""``labd migrate``: upgrade an archive's index in place to this labd's schema.

    labd migrate [--data DIR | --database URL] [--json]

``labd serve`` refuses an index of an older schema and names this command. It keeps
every row (``repository.migrate`` says how each changes), in one transaction. Stop the
lab (and its remote workers) first.
"""

from __future__ import annotations

import argparse
from typing import Any

from labd.commands import settings
from labd.commands.common import emit, fail, json_option
from labd.config import database_url
from repository.errors import ArchiveError
from repository.index import connect
from repository.migrate import upgrade


def add_parser(commands: Any) -> None:
    p = commands.add_parser("migrate", help="upgrade the archive's index to this labd's schema")
    settings.add(p, [settings.get("data"), settings.get("database")])
    json_option(p)


def main(args: argparse.Namespace) -> int:
    if args.database is None and not (args.data / "index.sqlite").exists():
        return fail(args, f"no archive in {args.data} (no index.sqlite); give --data or --database")
    engine = connect(database_url(args.data, args.database))
    try:
        done = upgrade(engine)
    except ArchiveError as err:
        return fail(args, str(err))
    finally:
        engine.dispose()
    data = {"before": done.before, "after": done.after, "changed": done.changed}
    emit(args, data, lambda: [str(done)])
    return 0
