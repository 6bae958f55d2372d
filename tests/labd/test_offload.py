"""Helper processes (``labd.offload``): calls, their errors, their time limits, a pool."""

from __future__ import annotations

import json
import os
import threading
import time

import pytest

from labd.offload import Helper, HelperError, Helpers


@pytest.fixture
def helper():
    made = Helper(name="test helper")
    yield made
    made.close()


def test_a_call_runs_in_the_child_and_returns_its_result(helper):
    assert helper.call("os:getpid") == helper.pid != os.getpid()
    assert helper.call("json:dumps", {"a": 1}, sort_keys=True) == '{"a": 1}'
    first = helper.pid
    helper.call("os:getpid")
    assert helper.pid == first  # one child, reused


def test_an_exception_in_the_child_is_raised_here_as_itself(helper):
    with pytest.raises(json.JSONDecodeError, match="Expecting property name"):
        helper.call("json:loads", "{not json")
    assert helper.call("json:loads", "[1]") == [1]  # the child goes on
    with pytest.raises(AttributeError):
        helper.call("json:no_such_function")


def test_a_call_past_its_time_kills_the_child_and_the_next_call_starts_another(helper):
    helper.call("os:getpid")
    first = helper.pid
    started = time.monotonic()
    with pytest.raises(TimeoutError, match=r"took longer than 0\.5 s"):
        helper.call("time:sleep", 30, timeout=0.5)
    assert time.monotonic() - started < 10
    with pytest.raises(ProcessLookupError):
        os.kill(first, 0)  # killed and reaped
    assert helper.call("os:getpid") != first


def test_a_child_that_dies_is_an_error_naming_how_and_is_started_again(helper):
    with pytest.raises(HelperError, match="exit status 3"):
        helper.call("os:_exit", 3)
    assert helper.call("json:loads", "2") == 2


def test_a_helper_runs_at_the_niceness_asked_for():
    low = Helper(nice=7)
    try:
        pid = low.call("os:getpid")
        assert os.getpriority(os.PRIO_PROCESS, pid) == os.getpriority(os.PRIO_PROCESS, 0) + 7
    finally:
        low.close()


def test_a_pool_starts_a_second_helper_only_while_the_first_is_busy():
    pool = Helpers(2)
    try:
        seen: list[int] = []

        def busy() -> None:
            pool.call("time:sleep", 1.0)
            seen.append(0)

        a = pool.call("os:getpid")
        thread = threading.Thread(target=busy)
        thread.start()
        while pool._idle.qsize():  # until the first helper is taken, asleep in its call
            time.sleep(0.001)
        b = pool.call("os:getpid")
        thread.join()
        assert a != b and set(pool.pids()) == {a, b} and seen == [0]
        assert pool.call("os:getpid") in {a, b}  # idle ones are reused
    finally:
        pool.close()
    assert pool.pids() == []


def test_an_idle_helper_is_of_the_idle_scheduling_class():
    idle = Helper(idle=True)
    try:
        pid = idle.call("os:getpid")
        assert os.sched_getscheduler(pid) == os.SCHED_IDLE
    finally:
        idle.close()
