"""A log that limits itself: a message repeated in a tight loop is let through a few
times a second, and the next one let through says how many were held back."""

from __future__ import annotations

import logging
import re
import subprocess
import sys

from labd.logs import RepeatLimit


class Clock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def record(msg: str, *args: object, name: str = "asyncio", level: int = logging.ERROR):
    return logging.LogRecord(name, level, __file__, 1, msg, args, None)


def test_a_repeated_message_is_held_back_and_counted():
    """Five at once, then two a second; the next one through counts those held back."""
    clock = Clock()
    limit = RepeatLimit(rate=2.0, burst=5, clock=clock)
    passed = [limit.filter(record("socket.accept() out of system resource")) for _ in range(1000)]
    assert passed.count(True) == 5
    clock.now += 0.5  # one more is due
    through = record("socket.accept() out of system resource")
    assert limit.filter(through)
    assert through.getMessage() == (
        "socket.accept() out of system resource [and 995 more like it in the last 0.5 s,"
        " not logged]"
    )
    assert not limit.filter(record("socket.accept() out of system resource"))


def test_one_message_with_changing_arguments_is_one_message():
    """The template is the key, so a flood of one message with new arguments is held too,
    and other messages, levels and loggers are not."""
    limit = RepeatLimit(rate=2.0, burst=5, clock=Clock())
    passed = [limit.filter(record("client %d left", n)) for n in range(100)]
    assert passed.count(True) == 5
    assert limit.filter(record("another message"))
    assert limit.filter(record("client %d left", 1, level=logging.WARNING))
    assert limit.filter(record("client %d left", 1, name="labd.bridge.server"))


def test_the_log_keeps_its_rate_over_time():
    """Over a minute of a message every millisecond, about two a second get through."""
    clock = Clock()
    limit = RepeatLimit(rate=2.0, burst=5, clock=clock)
    through = 0
    for _ in range(60_000):
        clock.now += 0.001
        through += limit.filter(record("Invalid HTTP request received.", name="uvicorn.error"))
    assert 5 + 2 * 60 - 2 <= through <= 5 + 2 * 60


def test_the_log_level_chosen_on_the_command_line_is_the_one_logged_at(tmp_path):
    """`labd --log-level DEBUG` logs debug messages in the lab's format, although a library
    (absl, at dm_control's first message) configured the root logger when it was imported."""
    command = [sys.executable, "-m", "labd", "--log-level", "DEBUG", "trials", "--server", "http://127.0.0.1:1"]  # fmt: skip
    runs = [  # at once: each retries for a few seconds before it gives up
        subprocess.Popen(c, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=tmp_path)
        for c in (command[:3] + command[5:], command)
    ]
    (_, quiet), (_, loud) = (run.communicate(timeout=60) for run in runs)
    assert all(run.returncode != 0 for run in runs)
    assert "cannot reach the lab" in quiet
    assert " DEBUG " not in quiet and " INFO " not in quiet  # the default: warnings and worse
    assert re.search(r"^\S+ \S+ DEBUG scheduler\.client: cannot reach", loud, re.M), loud
