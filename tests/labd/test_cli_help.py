"""Every option of every ``labd`` command says what it does and, if it has one, its default;
a wrong command line is answered by the command it names, with the nearest right word."""

from __future__ import annotations

import argparse

import pytest

from labd.cli import build_parser, main


def options():
    parser = build_parser()
    commands = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    for action in parser._actions:
        if not isinstance(action, argparse._HelpAction | argparse._SubParsersAction):
            yield "labd", parser, action
    for name, sub in commands.choices.items():
        for action in sub._actions:
            if isinstance(action, argparse._HelpAction | argparse._SubParsersAction):
                continue
            yield name, sub, action
        for inner in sub._actions:
            if isinstance(inner, argparse._SubParsersAction):
                for subname, subsub in inner.choices.items():
                    for action in subsub._actions:
                        if not isinstance(action, argparse._HelpAction):
                            yield f"{name} {subname}", subsub, action


def test_every_option_has_help_that_states_its_default():
    """No option is bare, and each with a default value names it in its help."""
    missing_help, missing_default = [], []
    for command, parser, action in options():
        flag = "/".join(action.option_strings) or action.dest
        if not action.help:
            missing_help.append(f"{command} {flag}")
            continue
        text = parser._get_formatter()._expand_help(action)
        has_default = action.default not in (None, False, [], argparse.SUPPRESS)
        if action.option_strings and has_default and "default" not in text:
            missing_default.append(f"{command} {flag}: {text}")
    assert missing_help == []
    assert missing_default == []


def test_the_check_sees_every_command():
    """The walk above reaches every command and its options (so it can fail)."""
    seen = {command for command, _, _ in options()}
    assert {"serve", "run", "submit", "trials", "users add", "migrate", "demo", "worker"} <= seen
    assert sum(1 for _ in options()) > 80


def test_an_unknown_command_is_answered_with_the_nearest_one(capsys):
    """``labd sumbit`` is a usage error (2) that suggests ``submit``."""
    with pytest.raises(SystemExit) as exited:
        main(["sumbit", "x"])
    assert exited.value.code == 2
    assert "did you mean 'submit'?" in capsys.readouterr().err


def test_a_command_s_usage_error_shows_that_command_s_usage(capsys):
    """An option a command does not take (``labd logs 2 --tail``) is reported by that
    command, with its usage, not by ``labd`` with the list of commands."""
    with pytest.raises(SystemExit) as exited:
        main(["logs", "2", "--tail"])
    assert exited.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith("usage: labd logs "), err
    assert err.rstrip().endswith("labd logs: error: unrecognized arguments: --tail"), err
