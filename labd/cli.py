"""The ``labd`` command: one module per command under ``labd.commands``.

    labd serve ...                 the lab: bridge, robots, HTTP API, archive, workers
    labd run PATH|URL ...          one trial, locally, with no server (the pre-flight)
    labd submit | trials | show | logs | download | rerun | cancel | export | tasks | status
                                   a running lab, through its HTTP API
    labd match | matches | ladder  two repositories play a task teams play; a task's ratings
    labd reserve book|list|extend|release|key
                                   book a live robot for a slot; its key
    labd users add|list|password|revoke|rotate
                                   the operator's: users, their passwords and tokens
    labd migrate                   the operator's: upgrade an archive's index in place
    labd backup DEST | restore SRC the operator's: copy the archive while it runs; bring it up
    labd config show               the operator's: the effective settings, and their sources
    labd replay TRIAL|RECORD       re-simulate a record from its actions; render its cameras
    labd verify FILE|DIR           check a record or an export against its signature, offline
    labd keys rotate               the operator's: sign with a new key
    labd worker --server URL       run a lab's trials on this machine
    labd demo                      what `make demo` runs
    labd demonstrate               scripted maze demonstrations, filed in the archive

Only the module of the command asked for is imported, so a command that talks to a lab
starts without the simulator. ``labd serve`` and the operator's commands read the lab's
configuration file and ``LABD_*`` variables (``labd.commands.config``); ``labd serve``'s
settings are declared once, in ``labd.commands.settings``.

Exit codes are listed in ``labd.commands.common`` and at the end of ``labd --help``.
"""

from __future__ import annotations

import argparse
import contextlib
import difflib
import faulthandler
import importlib
import io
import json
import logging
import os
import signal
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, NoReturn

from labd import __version__
from labd.commands import config, settings
from labd.commands.common import EPILOG, fail
from labd.logs import limit_repeats

log = logging.getLogger("labd")


@dataclass(frozen=True)
class Command:
    """A command of ``labd``: the module under ``labd.commands`` that defines and runs it
    (imported only when it is the one asked for), and its line in ``labd --help``."""

    module: str
    help: str


COMMANDS = {
    "serve": Command(
        "serve", "run the lab: the bridge and robots, the HTTP API, the archive and its workers"
    ),
    "run": Command("run", "run a controller repository as one trial, locally"),
    "submit": Command("remote", "queue a trial of a repository at a ref"),
    "trials": Command("remote", "list trials in the archive, newest first"),
    "show": Command("remote", "one trial: how it ended, what ran, its record"),
    "logs": Command("remote", "print a trial's controller output"),
    "download": Command("remote", "download a trial's MCAP record"),
    "rerun": Command("remote", "rerun a trial, or a commit's trials, to check them"),
    "cancel": Command("remote", "cancel a queued or running trial, or an evaluation"),
    "export": Command("export", "export trials for learning: a row per control tick, every camera"),
    "tasks": Command("remote", "the lab's tasks and their parameters"),
    "status": Command("remote", "the lab now: the queue and what workers run"),
    "evaluate": Command(
        "evaluate", "score a commit on a task's suite of episodes, with its uncertainty"
    ),
    "evaluations": Command("evaluate", "list evaluations, newest first"),
    "match": Command("match", "play two repositories against each other on a task teams play"),
    "matches": Command("match", "list matches, newest first"),
    "ladder": Command("match", "a task's ladder: commits rated from their matches"),
    "reserve": Command("reserve", "book a live robot for a slot; your bookings"),
    "users": Command("users", "the operator's: the lab's users, their passwords and tokens"),
    "suites": Command("suites", "the operator's: the tasks' episode suites"),
    "migrate": Command(
        "migrate", "the operator's: upgrade the archive's index to this labd's schema"
    ),
    "backup": Command("backup", "the operator's: a consistent copy of the archive, while it runs"),
    "restore": Command("backup", "the operator's: bring a backup up as a new lab"),
    "config": Command("config", "the operator's: the effective settings and their sources"),
    "keys": Command("verify", "the operator's: the keys the lab signs with"),
    "verify": Command("verify", "check a record or an export against its signature"),
    "replay": Command("replay", "re-simulate a record and compare; render videos"),
    "demo": Command("demo", "serve the lab, submit the examples, show results"),
    "demonstrate": Command(
        "demonstrate", "scripted maze demonstrations, filed in the lab's archive"
    ),
    "worker": Command("worker", "run a lab's queued trials on this machine"),
}


class Parser(argparse.ArgumentParser):
    """argparse's parser, whose usage errors are JSON when ``--json`` was asked for, which
    suggests the nearest choice for a wrong one (``labd sumbit``: did you mean 'submit'?),
    and whose commands report the words they do not take themselves, with their own
    usage (argparse leaves them to ``labd``, which shows the list of commands)."""

    def error(self, message: str) -> NoReturn:
        if "--json" in sys.argv[1:]:
            print(json.dumps({"error": f"{self.prog}: {message}"}))
            sys.exit(2)
        super().error(message)

    def _check_value(self, action: argparse.Action, value: Any) -> None:
        choices = action.choices
        if choices is not None and value not in choices:
            names = [str(choice) for choice in choices]
            near = difflib.get_close_matches(str(value), names, n=1)
            if near:
                commands = isinstance(action, argparse._SubParsersAction) and self.prog == "labd"
                listed = "`labd --help` lists them" if commands else ", ".join(names)
                raise argparse.ArgumentError(
                    action, f"invalid choice: {value!r}, did you mean {near[0]!r}? ({listed})"
                )
        super()._check_value(action, value)

    def parse_known_args(  # type: ignore[override]
        self, args: Sequence[str] | None = None, namespace: argparse.Namespace | None = None
    ) -> tuple[argparse.Namespace, list[str]]:
        parsed, extra = super().parse_known_args(args, namespace)
        if extra and self.prog != "labd":  # a command's: none is the next parser's to read
            self.error(f"unrecognized arguments: {' '.join(extra)}")
        return parsed, extra


def build_parser(argv: Sequence[str] | None = None) -> argparse.ArgumentParser:
    """The command line's parser. Only the module of the command ``argv`` names is
    imported (``labd --version`` and ``labd trials`` need no simulator); the other
    commands are listed by name. ``argv`` None: every command's module (the docs' tests)."""
    parser = Parser(
        prog="labd",
        description="The remote robot lab daemon.",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"labd {__version__}")
    settings.add(parser, settings.group(settings.LABD))  # --log-level
    commands = parser.add_subparsers(
        dest="command", required=True, metavar="COMMAND", parser_class=Parser
    )
    wanted = list(COMMANDS) if argv is None else [_command_in(argv)]
    for module in dict.fromkeys(COMMANDS[name].module for name in wanted if name in COMMANDS):
        _module(module).add_parser(_Listed(commands))
    for name, command in COMMANDS.items():
        if name not in commands.choices:
            commands.add_parser(name, help=command.help, add_help=False)
        elif name in config.CONFIGURED:
            for leaf in config.leaves(commands.choices[name]):
                config.add_config_option(leaf)
    return parser


class _Listed:
    """The commands' ``add_subparsers`` action, as a module sees it: its commands' lines
    in ``labd --help`` are ``COMMANDS``'s."""

    def __init__(self, commands: Any) -> None:
        self._commands = commands

    def add_parser(self, name: str, **options: Any) -> argparse.ArgumentParser:
        options["help"] = COMMANDS[name].help
        parser: argparse.ArgumentParser = self._commands.add_parser(name, **options)
        return parser


def _command_in(argv: Sequence[str]) -> str:
    """The command ``argv`` names: its first word that is no option (nor an option's value)."""
    words = iter(argv)
    for word in words:
        if word == "--log-level":
            next(words, None)
        elif not word.startswith("-"):
            return word
    return ""


def _module(name: str) -> Any:
    return importlib.import_module(f"labd.commands.{name}")


def main(argv: Sequence[str] | None = None) -> int:
    try:
        code = _main(argv)
        sys.stdout.flush()  # here, so a reader that left is noticed here
    except BrokenPipeError:
        # The reader went away (`labd trials | head`): stop quietly, as other tools do.
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 1
    except KeyboardInterrupt:
        return 130
    return code


def _main(argv: Sequence[str] | None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = build_parser(argv)
    args = parser.parse_args(argv)
    if args.command in config.CONFIGURED:
        try:
            config.apply(parser, args, config.given(build_parser, argv))
        except config.ConfigError as err:
            return fail(args, str(err))
    # force: a library may have configured the root logger on import (absl's logging
    # does, at dm_control's first message), which would make this call do nothing
    logging.basicConfig(
        level=args.log_level,
        stream=sys.stderr,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        force=True,
    )
    limit_repeats()  # a message repeated in a tight loop must not fill the disk
    # ``kill -USR1 PID`` prints where every thread of a labd process is, on stderr
    with contextlib.suppress(io.UnsupportedOperation, ValueError):  # (a captured stderr)
        faulthandler.register(signal.SIGUSR1, all_threads=True)
    run: Callable[[argparse.Namespace], int] = _module(COMMANDS[args.command].module).main
    return run(args)
