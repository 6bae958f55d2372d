"""Helper processes: work on filed records done beside the lab's process, not in it.

What is made of a filed record (its page summary, its replay's verdict, its camera's
video) is CPU-bound Python and C. Done in a thread of the process that also steps the
next trial's robot, it would take that robot's interpreter lock for milliseconds at a
time, and a lockstep tick is about one millisecond; done in a helper process, it runs on
another core and the next trial does not wait for it.

A ``Helper`` is one child process (``python -m labd.offload NICE``) that runs functions
named ``module:function``, one call at a time: the arguments and the result (or the
exception) go as pickles over its standard input and output. Its first call imports
what the function needs; later ones reuse it. A call that overruns its ``timeout`` kills
the child, and a child that dies is started again at the next call. ``Helpers`` is a
pool of them, started as calls need them; ``pool`` gives the pool of a purpose, shared
by everything in a process (each purpose keeps its own niceness).
"""

from __future__ import annotations

import atexit
import contextlib
import importlib
import logging
import os
import pickle
import queue
import select
import struct
import subprocess
import sys
import threading
import time
import traceback
from typing import Any

from labd.errors import LabError

log = logging.getLogger("labd.offload")
_HEADER = struct.Struct("!Q")


class HelperError(LabError):
    """A helper process that died, or that could not run the call."""


class Helper:
    """One child process that runs one call at a time."""

    def __init__(self, nice: int = 0, name: str = "helper", *, idle: bool = False) -> None:
        self.nice = nice
        self.idle = idle  # of the idle scheduling class: it runs only when nothing else would
        self.name = name
        self._process: subprocess.Popen[bytes] | None = None
        self._lock = threading.Lock()

    @property
    def pid(self) -> int | None:
        return None if self._process is None else self._process.pid

    def call(self, function: str, *args: Any, timeout: float | None = None, **kwargs: Any) -> Any:
        """``function(*args, **kwargs)`` in the child (``function`` is ``module:name``):
        its result, or its exception raised here. ``TimeoutError`` (the child killed) if
        it takes longer than ``timeout`` seconds; ``HelperError`` if the child dies."""
        with self._lock:
            process = self._started()
            assert process.stdin is not None and process.stdout is not None
            try:
                _write(process.stdin, (function, args, kwargs))
                kind, value = _read(process.stdout, timeout)
            except TimeoutError:
                self._kill()
                raise TimeoutError(f"{function} took longer than {timeout:g} s") from None
            except (OSError, EOFError, pickle.UnpicklingError) as err:
                code = self._kill()
                raise HelperError(
                    f"the {self.name} process ended while it ran {function} ({_ended(code)})"
                ) from err
        if kind == "error":
            raise value
        return value

    def _started(self) -> subprocess.Popen[bytes]:
        if self._process is None or self._process.poll() is not None:
            self._process = subprocess.Popen(  # noqa: S603 - this Python, running this module
                [sys.executable, "-m", "labd.offload", str(self.nice), "idle" if self.idle else ""],
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                close_fds=True,
            )
            log.debug("%s process %d started", self.name, self._process.pid)
        return self._process

    def _kill(self) -> int | None:
        process, self._process = self._process, None
        if process is None:
            return None
        with contextlib.suppress(ProcessLookupError):
            process.kill()
        code = process.wait()
        for stream in (process.stdin, process.stdout):
            if stream is not None:
                with contextlib.suppress(OSError):
                    stream.close()
        return code

    def close(self) -> None:
        """Stop the child (it ends when its input closes; killed if it does not)."""
        with self._lock:
            process, self._process = self._process, None
        if process is None:
            return
        with contextlib.suppress(OSError):
            assert process.stdin is not None
            process.stdin.close()
        try:
            process.wait(5)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()
        if process.stdout is not None:
            process.stdout.close()


class Helpers:
    """Up to ``size`` helpers; a call takes an idle one, starting one if none is idle."""

    def __init__(
        self, size: int, *, nice: int = 0, idle: bool = False, name: str = "helper"
    ) -> None:
        self.size = size
        self._idle: queue.LifoQueue[Helper] = queue.LifoQueue()
        self._all: list[Helper] = []
        self._lock = threading.Lock()
        self._free = threading.Semaphore(size)
        self.nice = nice
        self.idle = idle
        self.name = name

    def call(self, function: str, *args: Any, timeout: float | None = None, **kwargs: Any) -> Any:
        """As ``Helper.call``, on an idle helper (waiting for one if all are busy)."""
        self._free.acquire()
        try:
            try:
                helper = self._idle.get_nowait()
            except queue.Empty:
                helper = Helper(self.nice, self.name, idle=self.idle)
                with self._lock:
                    self._all.append(helper)
            try:
                return helper.call(function, *args, timeout=timeout, **kwargs)
            finally:
                self._idle.put(helper)
        finally:
            self._free.release()

    def pids(self) -> list[int]:
        with self._lock:
            return [h.pid for h in self._all if h.pid is not None]

    def close(self) -> None:
        with self._lock:
            helpers, self._all = self._all, []
        for helper in helpers:
            helper.close()


_pools: dict[str, Helpers] = {}
_pools_lock = threading.Lock()


def pool(purpose: str, size: int, *, nice: int = 0, idle: bool = False) -> Helpers:
    """The process's pool for ``purpose`` (made at its first use, closed at exit)."""
    with _pools_lock:
        found = _pools.get(purpose)
        if found is None:
            name = f"{purpose} helper"
            found = _pools[purpose] = Helpers(size, nice=nice, idle=idle, name=name)
        return found


@atexit.register
def _close_pools() -> None:
    with _pools_lock:
        pools = list(_pools.values())
        _pools.clear()
    for helpers in pools:
        helpers.close()


def _ended(code: int | None) -> str:
    if code is None:
        return "it was not running"
    if code < 0:
        return f"killed by signal {-code}"
    return f"exit status {code}"


def _write(stream: Any, value: Any) -> None:
    data = pickle.dumps(value, protocol=pickle.HIGHEST_PROTOCOL)
    stream.write(_HEADER.pack(len(data)) + data)
    stream.flush()


def _read(stream: Any, timeout: float | None) -> Any:
    deadline = None if timeout is None else time.monotonic() + timeout
    header = _read_exactly(stream, _HEADER.size, deadline)
    (size,) = _HEADER.unpack(header)
    # only ever between the lab's process and its own helper
    return pickle.loads(_read_exactly(stream, size, deadline))  # noqa: S301


def _read_exactly(stream: Any, size: int, deadline: float | None) -> bytes:
    fd = stream.fileno()
    chunks: list[bytes] = []
    left = size
    while left:
        if deadline is not None:
            wait = deadline - time.monotonic()
            if wait <= 0 or not select.select([fd], [], [], wait)[0]:
                raise TimeoutError
        chunk = os.read(fd, min(left, 1 << 20))
        if not chunk:
            raise EOFError
        chunks.append(chunk)
        left -= len(chunk)
    return b"".join(chunks)


def _serve(nice: int, idle: bool) -> None:
    """The child: answer calls until its input closes. Its results go to a copy of the
    standard output it was given; what the libraries print goes to standard error."""
    if nice:
        os.nice(nice)
    if idle:
        os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
    answers = os.fdopen(os.dup(1), "wb")
    os.dup2(2, 1)
    calls = sys.stdin.buffer
    while True:
        try:
            function, args, kwargs = _read(calls, None)
        except EOFError:
            return
        try:
            module, _, name = function.partition(":")
            result = ("ok", getattr(importlib.import_module(module), name)(*args, **kwargs))
        except Exception as err:  # noqa: BLE001 - the caller's to handle: sent back
            result = ("error", err)
            log.debug("%s failed:\n%s", function, traceback.format_exc())
        try:
            _write(answers, result)
        except (pickle.PicklingError, TypeError, AttributeError) as err:
            failed = result[1] if result[0] == "error" else err
            problem = HelperError(f"{function}: {type(failed).__name__}: {failed}")
            _write(answers, ("error", problem))


if __name__ == "__main__":
    _serve(int(sys.argv[1]) if len(sys.argv) > 1 else 0, sys.argv[2:3] == ["idle"])
