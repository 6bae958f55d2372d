"""What the ``labd`` commands share: exit codes, options, and how they print.

Exit codes (``labd --help`` lists them too):

    0  success: the trial achieved its task (a rerun: it reproduced); or the command did
       what it was asked
    1  fail: the trial ran to its end without achieving its task
    2  usage: a wrong command line, a request the lab refused, or no lab to talk to
    3  error: the trial broke (crashed, stalled, hit a limit, or the lab failed)
    4  cancelled: the trial was cancelled
    5  diverged: a rerun did not reproduce its original's data
    6  invalid: a record or an export does not match the lab's signature (labd verify)

With ``--json`` every command prints one JSON value on stdout, errors included
(``{"error": "..."}``), with the same exit code.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import re
import sys
from collections.abc import Callable, Iterable
from enum import IntEnum
from pathlib import Path
from typing import Any

from labd import config
from repository.trial import Outcome, Status
from scheduler.client import DEFAULT_SERVER


class ExitCode(IntEnum):
    SUCCESS = 0
    FAIL = 1
    USAGE = 2
    ERROR = 3
    CANCELLED = 4
    DIVERGED = 5
    INVALID = 6


EPILOG = """exit codes: 0 success (a rerun: reproduced; an evaluation: at least
--min-success); 1 fail (the trial ran to its end without achieving its task; an
evaluation below --min-success); 2 usage (a wrong command line, a refused request, no lab);
3 error (the trial broke; an evaluation partial, as the lab broke an episode); 4 cancelled;
5 a rerun did not reproduce; 6 a record or export does not match its signature (verify)"""


def exit_code(status: Status | str, outcome: Outcome | str | None) -> ExitCode:
    """The exit code of a command that waited for a trial that ended so."""
    if Status(status) is Status.CANCELLED:
        return ExitCode.CANCELLED
    return {
        Outcome.SUCCESS: ExitCode.SUCCESS,
        Outcome.FAIL: ExitCode.FAIL,
        Outcome.ERROR: ExitCode.ERROR,
    }[Outcome(outcome or Outcome.ERROR)]


def worst(codes: Iterable[ExitCode]) -> ExitCode:
    """One exit code for several trials: the most serious of theirs."""
    rank = [
        ExitCode.SUCCESS,
        ExitCode.FAIL,
        ExitCode.DIVERGED,
        ExitCode.CANCELLED,
        ExitCode.ERROR,
        ExitCode.USAGE,
    ]
    return max(codes, key=rank.index, default=ExitCode.SUCCESS)


def assignment(text: str) -> tuple[str, str]:
    """An argparse type: ``NAME=VALUE`` as a pair (``labd.config.assignment``), argparse
    saying what is wrong."""
    try:
        return config.assignment(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err)) from None


# What the lab takes for a URL rather than a path, as git does (scheduler.fetch's rule,
# copied so a client command need not import git; tests/labd/test_cli_repository_paths.py
# holds the two to each other): scheme://, transport::, or scp's [user@]host:path.
_SCHEME = re.compile(r"^([A-Za-z][A-Za-z0-9+.-]*)://")
_TRANSPORT = re.compile(r"^([A-Za-z][A-Za-z0-9+.-]*)::")
_SCP = re.compile(r"^(?:[^@/\s]+@)?(?:\[[0-9A-Fa-f:.]+\]|[\w.-]+):(?!//)")


def is_url(text: str) -> bool:
    """Whether a lab reads ``text`` as a repository's URL rather than a folder's path."""
    return any(rule.match(text) for rule in (_SCHEME, _TRANSPORT, _SCP))


def repository_arg(text: str) -> str:
    """An argparse type: a repository as the lab should read it. A URL as it is; a path
    is the caller's, so it is made absolute here, in the caller's folder (``~`` the
    caller's home, links followed, as the lab records a local repository), whether or
    not it exists: a lab on this machine then finds it, and one elsewhere names the
    whole path it did not find, never a folder of its own."""
    if not text or is_url(text):
        return text
    path = Path(text)
    with contextlib.suppress(RuntimeError):  # ~name of no user here: a folder's name then
        path = path.expanduser()
    return str(path.resolve())


REPOSITORY_HELP = "a git URL, or a local repository's folder (a relative path is from this folder)"


def param_option(
    parser: Any, help: str = "a task parameter (repeatable; default: the task's own values)"
) -> None:
    """``--param NAME=VALUE``, repeatable: ``args.param`` is a list of pairs."""
    parser.add_argument(
        "--param", action="append", default=[], type=assignment, metavar="NAME=VALUE", help=help
    )


def server_options(parser: argparse.ArgumentParser, *, write: bool = False) -> None:
    """``--server`` and ``--json``; with ``write``, ``--token`` too."""
    parser.add_argument(
        "--server",
        default=os.environ.get("LABD_SERVER", DEFAULT_SERVER),
        help="the lab's HTTP address (default: $LABD_SERVER, else %(default)s)",
    )
    parser.add_argument(
        "--json", action="store_true", help='print one JSON value, errors as {"error": ...}'
    )
    if write:
        parser.add_argument(
            "--token",
            default=os.environ.get("LABD_TOKEN"),
            help="your token (default: $LABD_TOKEN; the operator makes one with"
            " `labd users add NAME`)",
        )


def json_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--json", action="store_true", help='print one JSON value, errors as {"error": ...}'
    )


def emit(args: argparse.Namespace, data: Any, lines: Callable[[], Iterable[str]]) -> None:
    """Print ``data`` as JSON under ``--json``, else the lines a person reads."""
    if getattr(args, "json", False):
        print(json.dumps(data, indent=2, default=str))
    else:
        for line in lines():
            print(line)


def fail(args: argparse.Namespace, message: str, code: ExitCode = ExitCode.USAGE) -> int:
    """Report an error as the command's last word; its exit code."""
    if getattr(args, "json", False):
        print(json.dumps({"error": message}))
    else:
        print(f"labd {args.command}: {message}", file=sys.stderr)
    return int(code)
