"""What a lab fetches and how: the options ``labd serve`` and ``labd worker`` share."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from labd.config import assignment
from repository.units import MiB
from scheduler.fetch import Credential, FetchPolicy

DEFAULTS = FetchPolicy()


def add_options(group: Any) -> None:
    group.add_argument(
        "--allow-scheme",
        action="append",
        dest="schemes",
        metavar="SCHEME",
        help="repository URL schemes accepted (repeatable; default: "
        f"{' '.join(sorted(DEFAULTS.schemes))}; add http for plain HTTP)",
    )
    group.add_argument(
        "--allow-local-repos",
        action="store_true",
        help="accept local paths and file:// URLs as repositories: whoever may submit then"
        " reaches this machine's folders (default: refused; the lab's own are always refused)",
    )
    group.add_argument(
        "--allow-private-hosts",
        action="store_true",
        help="fetch from hosts at loopback, link-local and private addresses too: whoever"
        " may submit then reaches this machine's ports and its network (default: refused;"
        " the lab's own repositories are always fetched)",
    )
    group.add_argument(
        "--max-repo-mb",
        type=int,
        default=DEFAULTS.max_bytes // MiB,
        help="largest repository fetched, in MiB (default: %(default)s)",
    )
    group.add_argument(
        "--max-checkout-mb",
        type=int,
        default=DEFAULTS.max_checkout_bytes // MiB,
        help="largest commit checked out (its files added up, as written to disk), in MiB"
        " (default: %(default)s)",
    )
    group.add_argument(
        "--fetch-timeout",
        type=float,
        default=DEFAULTS.timeout,
        help="seconds a fetch may take (default: %(default)g)",
    )
    group.add_argument(
        "--submodule-allow",
        action="append",
        default=[],
        metavar="URL_PREFIX",
        help="submodules whose URL starts with this may be followed (repeatable; default: none)",
    )
    group.add_argument(
        "--git-token",
        action="append",
        default=[],
        metavar="URL_PREFIX=FILE",
        help="for private https repositories under URL_PREFIX: a token, read from FILE "
        "(repeatable; default: none); git alone sees it, never a controller",
    )
    group.add_argument(
        "--git-ssh-key",
        action="append",
        default=[],
        metavar="URL_PREFIX=KEYFILE",
        help="for private ssh repositories under URL_PREFIX: a deploy key (repeatable;"
        " default: none)",
    )


def argv(args: argparse.Namespace) -> list[str]:
    """The options of ``add_options`` as given, for another labd command (the worker
    processes ``labd serve`` starts fetch what it would)."""
    out: list[str] = []
    for scheme in args.schemes or ():
        out += ["--allow-scheme", scheme]
    if args.allow_local_repos:
        out.append("--allow-local-repos")
    if args.allow_private_hosts:
        out.append("--allow-private-hosts")
    out += ["--max-repo-mb", str(args.max_repo_mb), "--max-checkout-mb", str(args.max_checkout_mb)]
    out += ["--fetch-timeout", f"{args.fetch_timeout:g}"]
    for flag, items in (
        ("--submodule-allow", args.submodule_allow),
        ("--git-token", args.git_token),
        ("--git-ssh-key", args.git_ssh_key),
    ):
        for item in items:
            out += [flag, item]
    return out


def policy(args: argparse.Namespace, command: str) -> FetchPolicy:
    """The fetch policy the options describe (SystemExit with the reason if they are wrong)."""
    credentials = []
    for item in args.git_token:
        prefix, file = _pair(item, command, "--git-token", "URL_PREFIX=FILE")
        try:
            token = Path(file).read_text().strip()
        except OSError as err:
            raise SystemExit(f"{command}: --git-token {prefix}: {err}") from None
        credentials.append(Credential(prefix, token=token))
    for item in args.git_ssh_key:
        prefix, file = _pair(item, command, "--git-ssh-key", "URL_PREFIX=KEYFILE")
        if not Path(file).is_file():
            raise SystemExit(f"{command}: --git-ssh-key {prefix}: no key file {file}")
        credentials.append(Credential(prefix, ssh_key=Path(file).resolve()))
    schemes = frozenset(args.schemes) if args.schemes else DEFAULTS.schemes
    if "file" in schemes:
        raise SystemExit(f"{command}: --allow-scheme file: local paths are --allow-local-repos")
    if args.allow_local_repos:
        schemes |= {"file"}
    for flag, value in (
        ("--max-repo-mb", args.max_repo_mb),
        ("--max-checkout-mb", args.max_checkout_mb),
    ):
        if value <= 0:
            raise SystemExit(f"{command}: {flag} {value}: give a size of 1 MiB or more")
    return FetchPolicy(
        credentials=tuple(credentials),
        schemes=schemes,
        max_bytes=args.max_repo_mb * MiB,
        max_checkout_bytes=args.max_checkout_mb * MiB,
        timeout=args.fetch_timeout,
        submodules=tuple(args.submodule_allow),
        private_hosts=args.allow_private_hosts,
    )


def _pair(item: str, command: str, flag: str, form: str) -> tuple[str, str]:
    try:
        prefix, value = assignment(item, last=True)  # a URL prefix may hold a "="
    except ValueError:
        value = ""
    if not value:
        raise SystemExit(f"{command}: {flag} takes {form}, got {item!r}")
    return prefix, value
