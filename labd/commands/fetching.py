"""What a lab fetches and how: the settings ``labd serve`` and ``labd worker`` share
(``settings.FETCH``), and the fetch policy they make."""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path
from typing import Any

from labd.commands import settings
from labd.config import assignment
from scheduler.fetch import Credential, FetchPolicy

OPTIONS = settings.group(settings.FETCH)


def add_options(parser: Any) -> None:
    """The settings of what is fetched (``settings.FETCH``), in their group."""
    settings.add(parser, OPTIONS, grouped=True)


def argv(args: argparse.Namespace) -> list[str]:
    """The options of ``add_options`` as given, for another labd command (the worker
    processes ``labd serve`` starts fetch what it would)."""
    return settings.argv(args, OPTIONS)


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
    if "file" in args.allow_scheme:
        raise SystemExit(f"{command}: --allow-scheme file: local paths are --allow-local-repos")
    for flag, value in (
        ("--max-repo-mb", args.max_repo_mb),
        ("--max-checkout-mb", args.max_checkout_mb),
    ):
        if value <= 0:
            raise SystemExit(f"{command}: {flag} {value}: give a size of 1 MiB or more")
    found = settings.build(FetchPolicy, args, credentials=tuple(credentials))
    schemes = found.schemes or FetchPolicy().schemes  # an empty list in a file: the default
    return replace(found, schemes=schemes | {"file"} if args.allow_local_repos else schemes)


def _pair(item: str, command: str, flag: str, form: str) -> tuple[str, str]:
    try:
        prefix, value = assignment(item, last=True)  # a URL prefix may hold a "="
    except ValueError:
        value = ""
    if not value:
        raise SystemExit(f"{command}: {flag} takes {form}, got {item!r}")
    return prefix, value
