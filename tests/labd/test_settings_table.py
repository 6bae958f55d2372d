"""``labd serve``'s settings are declared once (``labd.commands.settings``): its flags, the
file's keys, the ``LABD_`` variables, ``labd config show``, the configuration objects the
lab runs with and the docs' list all come from the one table, each value converted from
the setting's unit to its field's; the commands never import the CLI back."""

from __future__ import annotations

import argparse
import ast
import dataclasses
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from labd.cli import build_parser
from labd.commands import config, fetching, serve, settings
from labd.config import BridgeConfig, DriveLimits, HttpConfig, RobotConfig
from labd.lab import LabConfig
from labd.service import ServiceConfig
from repository.reservations import Rules
from repository.units import MiB
from scheduler.data import DataPolicy
from scheduler.evaluate import HeldOutBudget
from scheduler.fetch import FetchPolicy
from scheduler.queue import QueueConfig

ROOT = Path(__file__).resolve().parents[2]
OBJECTS = [
    LabConfig,
    RobotConfig,
    BridgeConfig,
    HttpConfig,
    DriveLimits,
    ServiceConfig,
    QueueConfig,
    FetchPolicy,
    DataPolicy,
    HeldOutBudget,
    Rules,
]


def serve_args(*argv: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    serve.add_parser(parser.add_subparsers(dest="command"))
    return parser.parse_args(["serve", *argv])


def serve_config(*argv: str) -> LabConfig:
    return serve.config(serve_args(*argv))


def service_config(*argv: str) -> ServiceConfig:
    found = serve_config(*argv).service
    assert found is not None
    return found


def serve_flags() -> dict[str, argparse.Action]:
    parser = build_parser(["serve"])
    commands = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return {
        action.option_strings[0]: action
        for action in commands.choices["serve"]._actions
        if action.option_strings and action.dest not in ("help", "config")
    }


def test_each_row_is_one_flag_of_labd_serve_under_its_name():
    """labd serve's flags are the table's rows, each ``--name-with-dashes`` into
    ``args.name``, and nothing else; --log-level is labd's own, before the command."""
    flags = serve_flags()
    assert sorted(flags) == sorted(row.flag for row in settings.SERVE)
    assert all(flags[row.flag].dest == row.name for row in settings.SERVE)
    assert [row.name for row in settings.SETTINGS if row not in settings.SERVE] == ["log_level"]


def test_config_show_lists_every_row_and_a_variable_sets_each(tmp_path):
    """`labd config show` prints one setting a row, named as the row; LABD_NAME sets it."""
    clean = {k: v for k, v in os.environ.items() if not k.startswith("LABD_")}
    done = subprocess.run(
        [sys.executable, "-m", "labd", "config", "show", "--json"],
        capture_output=True,
        text=True,
        check=True,
        cwd=tmp_path,
        env={**clean, "LABD_LEASE": "12", "LABD_MAX_DRIVE_MB": "3"},
    )
    shown = json.loads(done.stdout)
    assert sorted(shown["settings"]) == sorted(row.name for row in settings.SETTINGS)
    assert shown["settings"]["lease"] == 12 and shown["sources"]["lease"] == "LABD_LEASE"
    assert shown["settings"]["max_drive_mb"] == 3


def test_every_row_sets_fields_that_exist_or_says_what_the_command_makes_of_it():
    """Each target is a field of a named configuration object, and a row without one
    says what becomes of it."""
    assert {cls.__name__ for cls in OBJECTS} == set(settings.OWNERS)
    for row in settings.SETTINGS:
        assert row.into or row.worked_out, row.name
        for target in row.into:
            cls = settings.owner(target.owner)
            assert target.name in {f.name for f in dataclasses.fields(cls)}, target


@pytest.mark.parametrize("row", settings.SETTINGS, ids=lambda row: row.name)
def test_a_rows_default_is_each_of_its_fields_defaults_in_its_unit(row):
    """One default: a row states the default of every field it sets, converted."""
    for target in row.into:
        assert settings.from_field(row, target, settings.field_default(target)) == (
            settings.default(row)
        ), target


@pytest.mark.parametrize("cls", OBJECTS, ids=lambda cls: cls.__name__)
def test_labd_serve_with_no_flags_runs_with_each_objects_own_defaults(cls):
    """The objects built from the settings' defaults hold, in every field a setting sets,
    the object's own default: no value is changed on its way through a flag."""
    args = serve_args()
    fields = settings.values(cls, args)
    built = {
        LabConfig: serve_config,
        RobotConfig: lambda: serve_config().robots[0],
        BridgeConfig: lambda: serve_config().bridge,
        HttpConfig: lambda: serve_config().http,
        DriveLimits: lambda: serve_config().drives,
        ServiceConfig: service_config,
        QueueConfig: lambda: service_config().queue,
        FetchPolicy: lambda: service_config().fetch,
        DataPolicy: lambda: service_config().data_policy,
        HeldOutBudget: lambda: service_config().held_out,
        Rules: lambda: service_config().rules,
    }[cls]()
    own = {
        f.name: settings.field_default(settings.Field(cls.__name__, f.name))
        for f in dataclasses.fields(cls)
        if f.name in fields
    }
    assert fields, f"no setting sets {cls.__name__}"
    assert {name: getattr(built, name) for name in fields} == own


@pytest.mark.parametrize(
    ("argv", "found", "expected"),
    [
        (["--max-drive-mb", "3"], lambda c: c.drives.max_record, 3 * MiB),
        (["--max-data-mb", "5"], lambda c: c.service.data_policy.max_bytes, 5 * MiB),
        (["--max-repo-mb", "7"], lambda c: c.service.fetch.max_bytes, 7 * MiB),
        (["--max-checkout-mb", "9"], lambda c: c.service.fetch.max_checkout_bytes, 9 * MiB),
        (["--max-slot", "30"], lambda c: c.service.rules.max_slot, 1800),
        (["--max-minutes-per-day", "45"], lambda c: c.service.rules.max_minutes_per_day, 45),
        (["--book-ahead", "2"], lambda c: c.service.rules.horizon, 2 * 86400),
        (["--max-slots-per-day", "0"], lambda c: c.service.rules.max_slots_per_day, None),
        (["--key-recheck", "0"], lambda c: c.bridge.key_recheck, None),
        (
            ["--header-timeout", "3"],
            lambda c: (c.http.header_timeout, c.bridge.handshake_timeout),
            (3, 3),
        ),
        (["--lease", "9"], lambda c: (c.service.queue.lease, c.service.heartbeat), (9, 3)),
        (["--no-playground"], lambda c: c.playground, False),
        (
            ["--reservations", "--no-watchers"],
            lambda c: (c.reservations, c.watchers),
            (True, False),
        ),
        (
            ["--lockstep", "--seed", "4"],
            lambda c: {(r.live, r.seed) for r in c.robots},
            {(False, 4)},
        ),
        (
            ["--protected-prefix", "/x", "--protected-prefix", "/y"],
            lambda c: c.bridge.protected_prefixes,
            ("/x", "/y"),
        ),
        (["--blobs-option", "a=b"], lambda c: c.service.blob_options, {"a": "b"}),
        (["--canary", "3", "--canary", "5"], lambda c: c.service.canaries, (3, 5)),
        (["--allow-scheme", "https"], lambda c: c.service.fetch.schemes, frozenset({"https"})),
        (["--allow-local-repos"], lambda c: "file" in c.service.fetch.schemes, True),
        (["--resolve-timeout", "7"], lambda c: c.service.fetch.resolve_timeout, 7),
        (["--held-out-per-day", "2"], lambda c: c.service.held_out.per_day, 2),
    ],
    ids=lambda value: " ".join(value) if isinstance(value, list) else "",
)
def test_a_setting_in_its_unit_becomes_its_field_in_the_fields_unit(argv, found, expected):
    """MiB become bytes, minutes and days seconds, 0 no limit, a switch its field's
    opposite where the field says the opposite; a repeatable flag replaces its default."""
    assert found(serve_config(*argv)) == expected


def test_a_field_is_set_by_a_setting_or_worked_out_never_both():
    """``build`` refuses a field given both ways: no setting is mapped twice by hand."""
    with pytest.raises(TypeError, match="max_record"):
        settings.build(DriveLimits, serve_args(), max_record=1)


def test_the_worker_processes_fetch_what_labd_serve_would(tmp_path):
    """serve's fetch settings, handed to `labd worker` as its command line, make the same
    fetch policy there (what ``--worker-processes`` start)."""
    token = tmp_path / "token"
    token.write_text("t0ken\n")
    args = serve_args(
        "--allow-scheme", "https", "--allow-scheme", "http", "--allow-private-hosts",
        "--max-repo-mb", "3", "--fetch-timeout", "2.5", "--submodule-allow", "https://x/",
        "--git-token", f"https://x/={token}",
    )  # fmt: skip
    argv = fetching.argv(args)
    worker = build_parser(["worker"]).parse_args(["worker", *argv])
    assert fetching.policy(worker, "labd worker") == fetching.policy(args, "labd serve")
    assert fetching.policy(worker, "labd worker").max_bytes == 3 * MiB


def test_data_and_database_are_the_tables_rows_in_every_command():
    """Every command that takes --data or --database takes the table's (its type, its
    metavar), save `labd run`'s folder of runs."""
    parser = build_parser()
    seen = set()
    for command, leaf in _leaves(parser):
        for action in leaf._actions:
            for row in (settings.get("data"), settings.get("database")):
                if row.flag in action.option_strings and command != "run":
                    assert (action.dest, action.metavar) == (row.name, row.metavar), command
                    assert action.type is (None if row.type is str else row.type), command
                    seen.add(command)
    assert {"serve", "users add", "keys rotate", "migrate", "suites list", "backup"} <= seen
    assert {"restore", "worker", "demo", "demonstrate"} <= seen


def _leaves(parser):
    commands = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    for name, sub in commands.choices.items():
        inner = [a for a in sub._actions if isinstance(a, argparse._SubParsersAction)]
        if not inner:
            yield name, sub
        for action in inner:
            for subname, leaf in action.choices.items():
                yield f"{name} {subname}", leaf


def test_no_module_imports_the_command_line_back():
    """Only ``labd.__main__`` imports ``labd.cli``: the commands and the table never do
    (``labd config show`` used to, the one run-time circle)."""
    importers = []
    for path in (ROOT / "labd").rglob("*.py"):
        tree = ast.parse(path.read_text(), str(path))
        for node in ast.walk(tree):
            names = (
                [alias.name for alias in node.names]
                if isinstance(node, ast.Import)
                else [node.module or ""]
                if isinstance(node, ast.ImportFrom)
                else []
            )
            if "labd.cli" in names:
                importers.append(path.relative_to(ROOT).as_posix())
    assert importers == ["labd/__main__.py"]


def test_an_operator_command_loads_none_of_the_lab_for_its_settings():
    """`labd users` shares data and database with the table without importing the lab's
    objects: their defaults are read only when a command asks for them."""
    probe = (
        "import sys; from labd.cli import build_parser; build_parser(['users'])"
        ".parse_args(['users', 'list']); print('labd.lab' in sys.modules,"
        " 'labd.service' in sys.modules)"
    )
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True)
    assert done.stdout.split() == ["False", "False"]


def test_the_docs_list_every_setting_as_the_table_says():
    """docs/operate.md's list of settings is the table's ``markdown()``, word for word."""
    text = (ROOT / "docs" / "operate.md").read_text()
    listed = text.split("holds it -->\n", 1)[1].split("<!-- end of settings -->", 1)[0]
    assert listed.strip() == settings.markdown().strip(), (
        "rewrite docs/operate.md's list from labd.commands.settings.markdown()"
    )


def test_config_show_needs_no_command_line_of_labd():
    """`labd config show` builds labd serve's options from the table alone."""
    parser = config.serve_parser()
    args = parser.parse_args(["serve"])
    assert args.log_level == "WARNING" and args.lease == QueueConfig().lease
