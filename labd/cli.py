"""The ``labd`` command: one module per command under ``labd.commands``.

    labd serve ...                 the lab: bridge, robots, HTTP API, archive, workers
    labd run PATH|URL ...          one trial, locally, with no server (the pre-flight)
    labd submit | trials | show | logs | download | rerun | cancel | export | tasks | status
                                   a running lab, through its HTTP API
    labd reserve book|list|extend|release|key
                                   book a live robot for a slot; its key
    labd users add|list|password|revoke|rotate
                                   the operator's: users, their passwords and tokens
    labd migrate                   the operator's: upgrade an archive's index in place
    labd replay TRIAL|RECORD       re-simulate a record from its actions; render its cameras
    labd verify FILE|DIR           check a record or an export against its signature, offline
    labd keys rotate               the operator's: sign with a new key
    labd worker --server URL       run a lab's trials on this machine
    labd demo                      what `make demo` runs
    labd demonstrate               scripted maze demonstrations, filed in the archive

Exit codes are listed in ``labd.commands.common`` and at the end of ``labd --help``.
"""

from __future__ import annotations

import argparse
import contextlib
import faulthandler
import io
import json
import logging
import os
import signal
import sys
from collections.abc import Callable, Sequence
from typing import NoReturn

from labd import __version__
from labd.commands import (
    demo,
    demonstrate,
    evaluate,
    migrate,
    remote,
    replay,
    reserve,
    run,
    serve,
    suites,
    users,
    verify,
    worker,
)
from labd.commands.common import EPILOG
from labd.logs import limit_repeats

log = logging.getLogger("labd")


class Parser(argparse.ArgumentParser):
    """argparse's parser, whose usage errors are JSON when ``--json`` was asked for."""

    def error(self, message: str) -> NoReturn:
        if "--json" in sys.argv[1:]:
            print(json.dumps({"error": f"{self.prog}: {message}"}))
            sys.exit(2)
        super().error(message)


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(
        prog="labd",
        description="The remote robot lab daemon.",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"labd {__version__}")
    parser.add_argument(
        "--log-level",
        default="WARNING",
        choices=["DEBUG", "INFO", "WARNING", "ERROR"],
        help="what the lab logs on stderr: INFO adds what it does, step by step"
        " (default: %(default)s)",
    )
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    serve.add_parser(commands)
    run.add_parser(commands)
    remote.add_parsers(commands)
    evaluate.add_parsers(commands)
    reserve.add_parser(commands)
    users.add_parser(commands)
    suites.add_parser(commands)
    migrate.add_parser(commands)
    verify.add_parser(commands)
    replay.add_parser(commands)
    demo.add_parser(commands)
    demonstrate.add_parser(commands)
    worker.add_parser(commands)
    return parser


MAINS: dict[str, Callable[[argparse.Namespace], int]] = {
    "serve": serve.main,
    "run": run.main,
    "reserve": reserve.main,
    "users": users.main,
    "suites": suites.main,
    "evaluate": evaluate.main,
    "evaluations": evaluate.main,
    "migrate": migrate.main,
    "verify": verify.main,
    "replay": replay.main,
    "keys": verify.main,
    "demo": demo.main,
    "demonstrate": demonstrate.main,
    "worker": worker.main,
    **dict.fromkeys(remote.COMMANDS, remote.main),
}


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
    args = build_parser().parse_args(argv)
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
    return MAINS[args.command](args)


if __name__ == "__main__":
    sys.exit(main())
