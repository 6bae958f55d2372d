"""One configuration for the lab: a TOML file, then ``LABD_*`` variables, then flags.

    labd serve --config /etc/labd/labd.toml
    labd users add carol --config /etc/labd/labd.toml
    labd config show [--config FILE] [--json]

``labd serve`` and the operator's commands (``CONFIGURED``) read the same file: its
``[serve]`` table is keyed by ``labd serve``'s settings (``labd.commands.settings``, one
row each; its long flags with underscores: ``http_port = 8080``, ``data = "/srv/lab"``,
``robot = ["icreate-1=icreate-maze"]``). An operator command takes from ``[serve]`` the
settings it has a flag for (``--data``, ``--database``, ``--blobs``...), so ``labd users
add`` opens the index the lab serves, never a second one; a table named after the command
(``[worker]``, ``[users]``) comes on top.

Each setting comes from the first of: its flag on the command line; the variable
``LABD_<FLAG>`` (``LABD_HTTP_PORT=8081``; a repeatable flag's values separated by commas;
a switch ``1``/``true``/``yes`` or ``0``/``false``/``no``); the file; the flag's default.
The file is ``--config FILE``, else ``$LABD_CONFIG``, else ``./labd.toml`` when there is
one. Relative paths in the file are relative to its folder. Every value goes through its
flag's own type, so the file is checked as strictly as the command line, and a key that is
no setting is an error that suggests the nearest name.

This is applied to the parsed command line from its flags (``apply``), which the table of
settings declares for ``labd serve`` and the shared ones, and each command for its own.
"""

from __future__ import annotations

import argparse
import difflib
import json
import os
import sys
import tomllib
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from labd.commands import settings
from repository.masking import MASK, SCHEME, mask_option, mask_url

DEFAULT_FILE = Path("labd.toml")
ENV_FILE = "LABD_CONFIG"
PREFIX = "LABD_"
# The commands that read the file and the environment: the lab and what its operator runs.
CONFIGURED = frozenset(
    {"serve", "users", "keys", "migrate", "reserve", "suites", "backup", "restore", "worker"}
)
# The commands that take the settings they share with ``labd serve`` from its table.
SHARING_SERVE = CONFIGURED - {"serve", "worker", "reserve"}
# Options that are about this run of the command, never settings.
NOT_SETTINGS = frozenset({"help", "version", "config", "json"})
SECRET_WORDS = ("token", "secret", "password", "passwd", "credential")
_WANTED: dict[Any, str] = {int: "not a whole number", float: "not a number"}
TRUE = frozenset({"1", "true", "yes", "on"})
FALSE = frozenset({"0", "false", "no", "off"})


class ConfigError(Exception):
    """A configuration that cannot be used; the message names the file, key or variable."""


@dataclass(frozen=True)
class Found:
    """One setting's effective value and where it came from: ``flag``, an environment
    variable's name, the file's ``path [table]``, or ``default``."""

    key: str
    value: Any
    source: str


# -- the argparse side ------------------------------------------------------------------------


def add_config_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--config",
        type=Path,
        metavar="FILE",
        help=f"the lab's configuration, TOML (default: ${ENV_FILE}, else ./{DEFAULT_FILE}"
        " when present; see docs/operate.md)",
    )


def chosen(
    parser: argparse.ArgumentParser, args: argparse.Namespace
) -> list[argparse.ArgumentParser]:
    """The parsers the command line went through: the top one, its command's, and each
    nested action's (``labd users add``: three)."""
    chain = [parser]
    while True:
        sub = next(
            (a for a in chain[-1]._actions if isinstance(a, argparse._SubParsersAction)), None
        )
        name = getattr(args, sub.dest, None) if sub is not None and sub.dest else None
        if sub is None or name is None or name not in sub.choices:
            return chain
        chain.append(sub.choices[name])


def leaves(parser: argparse.ArgumentParser) -> Iterator[argparse.ArgumentParser]:
    """Every parser under ``parser`` that has no commands of its own (``parser`` itself,
    when it has none)."""
    sub = next((a for a in parser._actions if isinstance(a, argparse._SubParsersAction)), None)
    if sub is None:
        yield parser
        return
    seen: set[int] = set()
    for child in sub.choices.values():
        if id(child) not in seen:  # an alias names the same parser twice
            seen.add(id(child))
            yield from leaves(child)


def options(parser: argparse.ArgumentParser) -> dict[str, argparse.Action]:
    """A parser's settings by key: each long flag's name with underscores."""
    found: dict[str, argparse.Action] = {}
    for action in parser._actions:
        longs = [o for o in action.option_strings if o.startswith("--")]
        key = longs[0][2:].replace("-", "_") if longs else ""
        if key and key not in NOT_SETTINGS:
            found[key] = action
    return found


def given(build: Any, argv: Sequence[str]) -> set[str]:
    """The destinations the command line itself set: ``argv`` parsed again by a fresh
    parser from ``build(argv)`` whose defaults all say nothing."""
    parser = build(argv)
    for each in _all_parsers(parser):
        each._defaults.clear()
        for action in each._actions:
            if not isinstance(action, argparse._SubParsersAction):
                action.default = argparse.SUPPRESS
    return set(vars(parser.parse_args(argv)))


def _all_parsers(parser: argparse.ArgumentParser) -> Iterator[argparse.ArgumentParser]:
    yield parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for child in action.choices.values():
                yield from _all_parsers(child)


# -- the file ---------------------------------------------------------------------------------


def config_path(args: argparse.Namespace, environ: Mapping[str, str]) -> Path | None:
    """The file this command reads: ``--config``, ``$LABD_CONFIG``, or ``./labd.toml``."""
    if getattr(args, "config", None) is not None:
        path: Path = args.config
    elif environ.get(ENV_FILE):
        path = Path(environ[ENV_FILE])
    elif DEFAULT_FILE.is_file():
        return DEFAULT_FILE
    else:
        return None
    if not path.is_file():
        raise ConfigError(f"{path}: no such configuration file")
    return path


def read(path: Path) -> dict[str, Any]:
    try:
        with path.open("rb") as f:
            return tomllib.load(f)
    except tomllib.TOMLDecodeError as err:
        raise ConfigError(f"{path}: not TOML: {err}") from None
    except OSError as err:
        raise ConfigError(f"{path}: {err.strerror}") from None


def _table(document: Mapping[str, Any], name: str, path: Path) -> dict[str, Any]:
    table = document.get(name, {})
    if not isinstance(table, dict):
        raise ConfigError(f"{path}: [{name}] must be a table")
    return table


# -- applying it ------------------------------------------------------------------------------


def apply(
    parser: argparse.ArgumentParser,
    args: argparse.Namespace,
    explicit: set[str],
    environ: Mapping[str, str] | None = None,
) -> dict[str, Found]:
    """Fill ``args`` from the environment and the file where the command line said
    nothing; every setting of the command with its source. ``ConfigError`` for a value
    that its flag would refuse, or a key of the command's own table that is no setting."""
    environ = os.environ if environ is None else environ
    chain = chosen(parser, args)
    command = chain[1].prog.split()[-1] if len(chain) > 1 else ""
    flags = {key: action for each in chain for key, action in options(each).items()}
    path = config_path(args, environ)
    args.config = path  # the file read, for the command to say
    document = read(path) if path is not None else {}
    tables: list[tuple[str, dict[str, Any]]] = []
    if path is not None:
        if command in SHARING_SERVE:
            tables.append(("serve", _table(document, "serve", path)))
        own = _table(document, command, path)
        _check_keys(own, flags, f"{path}: [{command}]", command)
        tables.append((command, own))
    found: dict[str, Found] = {}
    for key, action in flags.items():
        variable = PREFIX + key.upper()
        if action.dest in explicit:
            found[key] = Found(key, getattr(args, action.dest), "flag")
            continue
        if variable in environ:
            value = _from_text(action, environ[variable], variable)
            found[key] = Found(key, value, variable)
        else:
            for name, table in reversed(tables):
                if key in table:
                    assert path is not None
                    where = f"{path} [{name}] {key}"
                    value = _from_toml(action, table[key], where, path.parent)
                    found[key] = Found(key, value, f"{path} [{name}]")
                    break
            else:
                found[key] = Found(key, getattr(args, action.dest, None), "default")
                continue
        setattr(args, action.dest, value)
    return found


def _check_keys(
    table: Mapping[str, Any], flags: Mapping[str, argparse.Action], where: str, command: str
) -> None:
    for key in table:
        if key not in flags:
            near = difflib.get_close_matches(key, list(flags), n=1)
            hint = f" (did you mean {near[0]}?)" if near else ""
            raise ConfigError(f"{where} {key}: no setting of labd {command}{hint}")


def _switch(action: argparse.Action) -> bool:
    return isinstance(action, argparse._StoreTrueAction | argparse._StoreFalseAction)


def _repeatable(action: argparse.Action) -> bool:
    return isinstance(action, argparse._AppendAction)


def _convert(action: argparse.Action, text: Any, where: str) -> Any:
    """One value through the flag's own type and choices, as argparse would."""
    kind = action.type
    try:
        value = kind(text) if callable(kind) else text
    except (argparse.ArgumentTypeError, TypeError, ValueError) as err:
        why = (
            str(err)
            if isinstance(err, argparse.ArgumentTypeError)
            else _WANTED.get(kind, "refused")
        )
        raise ConfigError(f"{where}: {text!r}: {why}") from None
    if action.choices is not None and value not in action.choices:
        choices = ", ".join(map(str, action.choices))
        raise ConfigError(f"{where}: {value!r} is not one of {choices}")
    return value


def _from_text(action: argparse.Action, text: str, where: str) -> Any:
    """A value from an environment variable."""
    if _switch(action):
        word = text.strip().lower()
        if word not in TRUE | FALSE:
            raise ConfigError(f"{where}={text!r}: give 1 or 0 (true or false)")
        on = word in TRUE
        return on if isinstance(action, argparse._StoreTrueAction) else not on
    if _repeatable(action):
        return [_convert(action, part.strip(), where) for part in text.split(",") if part.strip()]
    return _convert(action, text, where)


def _from_toml(action: argparse.Action, value: Any, where: str, base: Path) -> Any:
    """A value from the file: TOML's own types where they fit, else text through the
    flag's type; a repeatable flag takes a list (or, for NAME=VALUE flags, a table)."""
    if _switch(action):
        if not isinstance(value, bool):
            raise ConfigError(f"{where}: give true or false")
        return value if isinstance(action, argparse._StoreTrueAction) else not value
    if _repeatable(action):
        if isinstance(value, dict):
            value = [f"{name}={item}" for name, item in value.items()]
        elif not isinstance(value, list):
            value = [value]
        return [_one(action, item, where, base) for item in value]
    return _one(action, value, where, base)


def _one(action: argparse.Action, value: Any, where: str, base: Path) -> Any:
    if isinstance(value, bool | dict | list):
        raise ConfigError(f"{where}: {value!r} is not a value this setting takes")
    if action.type in (int, float) and isinstance(value, int | float):
        if action.type is int and isinstance(value, float):
            raise ConfigError(f"{where}: {value!r}: give a whole number")
        return _convert(action, value, where)
    if isinstance(value, int | float) and action.type is None:
        value = str(value)
    if not isinstance(value, str):
        raise ConfigError(f"{where}: {value!r}: give text")
    converted = _convert(action, value, where)
    if isinstance(converted, Path) and not converted.is_absolute():
        return base / converted
    return converted


# -- showing it -------------------------------------------------------------------------------


def masked(key: str, value: Any) -> Any:
    """A value as ``labd config show`` prints it (``repository.masking``): a setting named
    for a secret (``--git-token``) masked whole; a ``NAME=VALUE`` pair's value masked
    whole when its name suggests a secret, as a URL when it is one; a URL's password,
    query and fragment values masked. ``NAME=VALUE`` pairs are shown as text."""
    if value is None or isinstance(value, bool | int | float):
        return value
    if isinstance(value, list | tuple) and not _pair(value):
        return [masked(key, item) for item in value]
    if any(word in key.lower() for word in SECRET_WORDS):
        return MASK
    if _pair(value):
        name, item = value
        return f"{name}={mask_option(name, item)}"
    text = str(value)
    if SCHEME.match(text) is None:
        name, sep, item = text.partition("=")
        if sep:
            return f"{name}={mask_option(name, item)}"
    return mask_url(text)


def _pair(value: Any) -> bool:
    """Whether ``value`` is a parsed ``NAME=VALUE`` option (``assignment``'s pair)."""
    return isinstance(value, tuple) and len(value) == 2 and all(isinstance(v, str) for v in value)


def add_parser(commands: Any) -> None:
    p = commands.add_parser(
        "config", help="the operator's: the lab's effective settings and where each came from"
    )
    actions = p.add_subparsers(dest="action", required=True, metavar="ACTION")
    show = actions.add_parser(
        "show", help="every setting of labd serve: its value, and its source (secrets masked)"
    )
    add_config_option(show)
    show.add_argument(
        "--json", action="store_true", help='print one JSON value, errors as {"error": ...}'
    )


def main(args: argparse.Namespace) -> int:
    parser = serve_parser()
    serve_args = parser.parse_args(["serve"])
    serve_args.config = args.config
    try:
        found = apply(parser, serve_args, explicit=set())
        path = config_path(serve_args, os.environ)
    except ConfigError as err:
        if args.json:
            print(json.dumps({"error": str(err)}))
        else:
            print(f"labd config: {err}", file=sys.stderr)
        return 2
    shown = {key: masked(key, s.value) for key, s in sorted(found.items())}
    if args.json:
        sources = {key: s.source for key, s in sorted(found.items())}
        print(
            json.dumps(
                {"file": str(path) if path else None, "settings": shown, "sources": sources},
                indent=2,
            )
        )
        return 0
    print(f"# labd serve's settings; file: {path if path else 'none'}")
    width = max(len(key) for key in shown)
    for key, value in shown.items():
        print(f"{key:<{width}} = {json.dumps(value)}  # {found[key].source}")
    return 0


def serve_parser() -> argparse.ArgumentParser:
    """A command line of ``labd serve`` alone: its settings, from the table."""
    parser = argparse.ArgumentParser(prog="labd")
    settings.add(parser, settings.group(settings.LABD))
    commands = parser.add_subparsers(dest="command")
    settings.add(commands.add_parser("serve"), settings.SERVE)
    return parser
