"""``labd users``: the operator's commands for the lab's users and their tokens.

    labd users add NAME [--password] [--worker] [--max-running N] [--max-daily N]
    labd users list
    labd users password NAME          set (or reset) the password to sign in on the pages;
                                      every browser signed in as NAME is signed out
    labd users revoke NAME [--token ID]
                                      revoke one token; or every token, browser session
                                      and reservation key (connected clients are cut off
                                      within labd serve's --key-recheck)
    labd users rotate NAME            revoke every token and print one new token

They write to the lab's database directly (the operator's commands, run where the lab
runs), so they take ``--data`` or ``--database`` as ``labd serve`` does. Only hashes of
tokens and passwords are kept: a token is printed once. A password is read from the
terminal (twice), or from standard input with ``--password-stdin``.
"""

from __future__ import annotations

import argparse
import getpass
import json
import sys
from typing import Any

from labd.commands import settings
from labd.commands.common import emit, fail, json_option
from labd.config import database_url
from repository.accounts import Accounts
from repository.errors import ArchiveError
from repository.index import Index, UserLimits
from repository.units import moment

USER = UserLimits()


class NoPassword(Exception):
    """No password could be read; the message says how to give one."""


def _where(parser: argparse.ArgumentParser) -> None:
    settings.add(parser, [settings.get("data"), settings.get("database")])
    json_option(parser)


def _password_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--password-stdin",
        action="store_true",
        help="read the password from the first line of standard input (default: ask twice"
        " on the terminal)",
    )


def add_parser(commands: Any) -> None:
    users = commands.add_parser("users", help="the lab's users, their passwords and tokens")
    actions = users.add_subparsers(dest="action", required=True)
    add = actions.add_parser("add", help="add a user and print their token")
    add.add_argument(
        "name",
        help="ASCII letters, digits, '-', '_' or '.', starting with a letter or a digit;"
        " new without case",
    )
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
    add.add_argument(
        "--password",
        action="store_true",
        help="also set a password, to sign in on the pages (default: a token only)",
    )
    _password_options(add)
    _where(add)

    listing = actions.add_parser("list", help="every user, with their tokens (never the tokens)")
    _where(listing)

    password = actions.add_parser(
        "password", help="set a user's password for the pages (their sign-ins end)"
    )
    password.add_argument("name", help="the user")
    _password_options(password)
    _where(password)

    revoke = actions.add_parser(
        "revoke",
        help="revoke a user's tokens (all, with their sign-ins and reservation keys, or"
        " --token ID)",
    )
    revoke.add_argument("name", help="the user")
    revoke.add_argument("--token", type=int, metavar="ID", help="only this token (its #id)")
    _where(revoke)

    rotate = actions.add_parser("rotate", help="revoke every token of a user; print a new one")
    rotate.add_argument("name", help="the user")
    _where(rotate)

    link = actions.add_parser(
        "link", help="let a person an OpenID provider vouches for sign in to a user's account"
    )
    link.add_argument("name", help="the user")
    link.add_argument("--issuer", required=True, metavar="URL", help="the provider's issuer")
    link.add_argument(
        "--subject", required=True, metavar="SUB", help="the person's subject there (its sub)"
    )
    link.add_argument("--email", default="", help="their e-mail, for the list (default: none)")
    _where(link)


def main(args: argparse.Namespace) -> int:
    if args.database is None and not (args.data / "index.sqlite").exists():
        print(
            f"labd users: {args.data} held no archive: a new one is made there (a lab"
            " elsewhere: give its --config, or its --data and --database)",
            file=sys.stderr,
        )
    args.data.mkdir(mode=0o700, parents=True, exist_ok=True)
    try:
        index = Index.open(database_url(args.data, args.database))
        try:
            return ACTIONS[args.action](args, index, Accounts(index))
        finally:
            index.close()
    except (ArchiveError, NoPassword) as err:
        return fail(args, str(err))


def _add(args: argparse.Namespace, index: Index, accounts: Accounts) -> int:
    password = _read_password(args) if args.password or args.password_stdin else None
    token = index.add_user(
        args.name, max_running=args.max_running, max_daily=args.max_daily, worker=args.worker
    )
    if password is not None:
        accounts.set_password(args.name, password)
    if args.json:
        print(json.dumps({"name": args.name, "token": token, "password": password is not None}))
    else:
        print(token)
        print(f"(user {args.name}; the lab keeps only a hash: save this token)", file=sys.stderr)
    return 0


def _list(args: argparse.Namespace, index: Index, accounts: Accounts) -> int:
    rows: list[dict[str, Any]] = []
    for user in index.users_list():
        tokens = accounts.tokens(user.name)
        rows.append(
            {
                "name": user.name,
                "created": _when(user.created),
                "worker": user.worker,
                "password": accounts.has_password(user.name),
                "identities": [
                    {"issuer": i.issuer, "subject": i.subject, "email": i.email}
                    for i in accounts.identities(user.name)
                ],
                "max_running": user.max_running,
                "max_daily": user.max_daily,
                "tokens": [
                    {
                        "id": t.id,
                        "label": t.label,
                        "created": _when(t.created),
                        "revoked": None if t.revoked is None else _when(t.revoked),
                    }
                    for t in tokens
                ],
            }
        )

    def lines() -> list[str]:
        out = []
        for row in rows:
            working = [t for t in row["tokens"] if t["revoked"] is None]
            what = ["worker"] if row["worker"] else []
            what.append("password" if row["password"] else "no password")
            what += [f"signs in through {i['issuer']}" for i in row["identities"]]
            what.append(f"{len(working)} of {len(row['tokens'])} tokens working")
            out.append(f"{row['name']:<20} {', '.join(what)}; since {row['created']}")
            for t in row["tokens"]:
                state = f"revoked {t['revoked']}" if t["revoked"] else "works"
                out.append(f"    token #{t['id']} {t['label']} ({t['created']}): {state}")
        return out or ["no users yet: labd users add NAME"]

    emit(args, rows, lines)
    return 0


def _password(args: argparse.Namespace, index: Index, accounts: Accounts) -> int:
    ended = accounts.set_password(args.name, _read_password(args))
    emit(
        args,
        {"name": args.name, "password": True, "sessions_ended": ended},
        lambda: [f"{args.name}: password set; {ended} signed-in browsers signed out"],
    )
    return 0


def _revoke(args: argparse.Namespace, index: Index, accounts: Accounts) -> int:
    if args.token is not None:
        token = accounts.revoke_token(args.name, args.token)
        data = {"name": args.name, "revoked": [token.id]}
        emit(args, data, lambda: [f"{args.name}: token #{token.id} ({token.label}) revoked"])
        return 0
    count = accounts.revoke_all(args.name)
    emit(
        args,
        {"name": args.name, "revoked": count},
        lambda: [
            f"{args.name}: {count} tokens revoked, every sign-in ended, and the keys of"
            " their booked slots replaced"
        ],
    )
    return 0


def _rotate(args: argparse.Namespace, index: Index, accounts: Accounts) -> int:
    token = accounts.rotate(args.name)
    if args.json:
        print(json.dumps({"name": args.name, "token": token}))
    else:
        print(token)
        print(f"({args.name}: every other token revoked; save this one)", file=sys.stderr)
    return 0


def _link(args: argparse.Namespace, index: Index, accounts: Accounts) -> int:
    accounts.link_identity(args.name, args.issuer, args.subject, args.email)
    emit(
        args,
        {"name": args.name, "issuer": args.issuer, "subject": args.subject},
        lambda: [f"{args.name}: {args.subject} of {args.issuer} signs in to this account"],
    )
    return 0


ACTIONS = {
    "add": _add,
    "list": _list,
    "password": _password,
    "revoke": _revoke,
    "rotate": _rotate,
    "link": _link,
}


def _read_password(args: argparse.Namespace) -> str:
    if args.password_stdin:
        line = sys.stdin.readline().rstrip("\n")
        if not line:
            raise NoPassword("no password on standard input (--password-stdin reads one line)")
        return line
    if not sys.stdin.isatty():
        raise NoPassword("no terminal to ask for the password on: give --password-stdin")
    first = getpass.getpass("password: ")
    if first != getpass.getpass("again: "):
        raise NoPassword("the two passwords differ")
    return first


def _when(seconds: float) -> str:
    return moment(seconds).strftime("%Y-%m-%d %H:%M UTC")
