"""Every limit docs/reservations.md and docs/protocol.md state about accounts, keys and
reservations is the default the code runs with (as tests/faults/test_documented_limits.py
does for the others), so a change to either fails here until both say it."""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path

import pytest

from labd.api.throttle import LIMITS
from labd.commands import serve
from labd.config import BridgeConfig
from labd.lab import LabConfig
from repository.accounts import MIN_PASSWORD, SESSION_AGE
from repository.reservations import MAX_HORIZON, MAX_SLOT, Rules

DOCS = Path(__file__).resolve().parents[2] / "docs"
BRIDGE, RULES = BridgeConfig(), Rules()


def served(*argv: str) -> Rules:
    parser = argparse.ArgumentParser()
    serve.add_parser(parser.add_subparsers(dest="command"))
    args = parser.parse_args(["serve", *argv])
    config = serve.service_config(args)
    assert config is not None
    return config.rules


def served_lab(*argv: str) -> LabConfig:
    parser = argparse.ArgumentParser()
    serve.add_parser(parser.add_subparsers(dest="command"))
    return serve.config(parser.parse_args(["serve", *argv]))


ROWS: list[tuple[str, str, Callable[[], object], object]] = [
    ("reservations.md", "| `--max-slot MIN` | 60 |", lambda: (RULES.max_slot, served().max_slot), (3600, 3600)),
    ("reservations.md", "| `--max-slots-per-day N` | 4 |", lambda: served().max_slots_per_day, 4),
    ("reservations.md", "| `--max-minutes-per-day MIN` | 120 |", lambda: served().max_minutes_per_day, 120),
    ("reservations.md", "| `--max-slots-per-week N` | 12 |", lambda: served().max_slots_per_week, 12),
    ("reservations.md", "| `--max-minutes-per-week MIN` | 480 |", lambda: served().max_minutes_per_week, 480),
    ("reservations.md", "| `--book-ahead DAYS` | 14 |", lambda: served().horizon, 14 * 86400),
    ("reservations.md", "A limit of 0 means no limit.", lambda: served("--max-slots-per-day", "0").max_slots_per_day, None),
    ("reservations.md", "one asked for up to a minute ago", lambda: RULES.grace, 60),
    ("reservations.md", "a password of at least 10 characters", lambda: MIN_PASSWORD, 10),
    ("reservations.md", "and its end (14 days)", lambda: SESSION_AGE, 14 * 86400),
    ("reservations.md", "five wrong passwords for one name from one address within five minutes",
     lambda: (LIMITS["password"].limit, LIMITS["password"].window), (5, 300)),
    ("reservations.md", "At most **5 accounts an hour are made from one address**",
     lambda: (LIMITS["signup"].limit, LIMITS["signup"].window), (5, 3600)),
    ("reservations.md", "how far ahead a slot may start (at most 365)", lambda: MAX_HORIZON, 365 * 86400),
    ("reservations.md", "at most this long (at most 1,440: a day)", lambda: MAX_SLOT, 1440 * 60),
    ("reservations.md", "(`labd serve --trusted-proxy ADDR`, an address or network, repeatable; default none)",
     lambda: served_lab().trusted_proxies, ()),
    ("protocol.md", "every 5 s (`labd serve --key-recheck S`; 0: never)",
     lambda: (BRIDGE.key_recheck, served_lab().bridge.key_recheck), (5, 5)),
    ("reservations.md", "or twenty failed sign-ins from one address",
     lambda: (LIMITS["address"].limit, LIMITS["address"].window), (20, 300)),
    ("protocol.md", "gets a status of level `warning` 60 s before its key's time ends",
     lambda: BRIDGE.expiry_warning, 60),
    ("protocol.md", "After 20 keys it never made from one address within 60 s",
     lambda: (LIMITS["key"].limit, LIMITS["key"].window), (20, 60)),
    ("protocol.md", "After 10 refused keys from one address within 60 s",
     lambda: (BRIDGE.auth_failures, BRIDGE.auth_failure_window), (10, 60)),
]  # fmt: skip


@pytest.mark.parametrize(
    ("doc", "sentence", "value", "stated"), ROWS, ids=[f"{r[0]}: {r[1]}" for r in ROWS]
)
def test_the_docs_state_the_default(doc, sentence, value, stated):
    """The sentence is in the doc, and the code's default is the figure it states."""
    text = " ".join((DOCS / doc).read_text().split())
    assert " ".join(sentence.split()) in text, f"{doc} no longer says {sentence!r}"
    assert value() == stated
