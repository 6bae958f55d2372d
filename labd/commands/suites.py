"""``labd suites``: the operator's commands for the tasks' episode suites.

    labd suites list [TASK]             every suite: version, episodes, held out, retired
    labd suites seeds TASK SUITE        a suite's seeds (a held-out suite's are the lab's
                                        secret: only the operator sees them, here)
    labd suites retire TASK SUITE [--version N]
                                        retire a held-out suite version: its episodes'
                                        seeds and records become public, like any trial's,
                                        and it takes no new evaluation

They read the lab's database and keys directly (run where the lab runs), so they take
``--data`` or ``--database`` as ``labd serve`` does. A held-out suite's seeds derive
from the secret ``DATA/keys/suites.secret``: keep it with the lab's keys; a lab that
loses it derives other seeds, so its held-out suites need a new version.
"""

from __future__ import annotations

import argparse
from collections.abc import Iterator
from typing import Any

from labd.commands import settings
from labd.commands.common import ExitCode, emit, fail, json_option
from labd.errors import LabError
from labd.sim import registry
from repository.errors import ArchiveError
from repository.evaluation import Suite
from repository.evaluation_index import Evaluations
from repository.index import Index
from repository.reservations import load_secret


def add_parser(commands: Any) -> None:
    suites = commands.add_parser("suites", help="the operator's: the tasks' episode suites")
    actions = suites.add_subparsers(dest="action", required=True)
    listing = actions.add_parser("list", help="every suite, and which are retired")
    listing.add_argument("task", nargs="?", help="only this task's (default: every task's)")
    _where(listing)
    seeds = actions.add_parser("seeds", help="a suite's seeds, held-out ones included")
    _task_and_suite(seeds)
    _where(seeds)
    retire = actions.add_parser(
        "retire", help="make a held-out suite version public; it takes no new evaluation"
    )
    _task_and_suite(retire)
    retire.add_argument(
        "--version", type=int, help="the suite version (default: the one the lab runs now)"
    )
    _where(retire)


def _task_and_suite(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("task", help="a task (`labd tasks` lists them)")
    parser.add_argument("suite", help="one of its suites (`labd suites list` lists them)")


def _where(parser: argparse.ArgumentParser) -> None:
    settings.add(parser, [settings.get("data"), settings.get("database")])
    json_option(parser)


def main(args: argparse.Namespace) -> int:
    if args.database is None and not (args.data / "index.sqlite").exists():
        return fail(args, f"no archive in {args.data} (no index.sqlite); give --data or --database")
    try:
        index = Index.open(args.database or f"sqlite:///{(args.data / 'index.sqlite').resolve()}")
    except ArchiveError as err:
        return fail(args, str(err))
    try:
        evaluations = Evaluations(index, lambda _digest: None)
        if args.action == "list":
            return _list(args, evaluations)
        suite = _suite(args.task, args.suite)
        if args.action == "seeds":
            secret = load_secret(args.data / "keys" / "suites.secret")
            seeds = suite.seeds_with(secret, args.task)
            said = {"task": args.task, "suite": suite.name, "version": suite.version}
            emit(args, {**said, "seeds": seeds}, lambda: (str(s) for s in seeds))
            return ExitCode.SUCCESS
        version = args.version or suite.version
        if not suite.held_out:
            return fail(args, f"suite {suite.name} of {args.task} is public: nothing to retire")
        made_public = evaluations.retire(args.task, suite.name, version)
        emit(
            args,
            {"task": args.task, "suite": suite.name, "version": version, "public": made_public},
            lambda: [
                f"retired {args.task} suite {suite.name} version {version}: {made_public}"
                " held-out episodes are public now; it takes no new evaluation"
            ],
        )
        return ExitCode.SUCCESS
    except (LabError, ArchiveError, ValueError) as err:
        return fail(args, str(err))
    finally:
        index.close()


def _suite(task: str, name: str) -> Suite:
    spec = registry.get(task)
    found = spec.suite(name)
    if found is None:
        known = ", ".join(s.name for s in spec.suites) or "none"
        raise ValueError(f"task {task} has no suite {name!r}; its suites: {known}")
    return found


def _list(args: argparse.Namespace, evaluations: Evaluations) -> int:
    tasks = [args.task] if args.task else registry.names()
    rows = []
    for task in tasks:
        spec = registry.get(task)
        retired = evaluations.retired(spec.name)
        for s in spec.suites:
            rows.append(
                {
                    "task": spec.name,
                    "suite": s.name,
                    "version": s.version,
                    "episodes": s.episodes,
                    "held_out": s.held_out,
                    "retired": (s.name, s.version) in retired,
                }
            )

    def lines() -> Iterator[str]:
        for r in rows:
            kind = "held out" if r["held_out"] else "public"
            gone = ", retired" if r["retired"] else ""
            where = f"{r['task']} {r['suite']} version {r['version']}"
            yield f"{where}: {r['episodes']} episodes, {kind}{gone}"

    emit(args, rows, lines)
    return ExitCode.SUCCESS
