"""How a trial ended, in a sentence a person can act on.

``judge`` turns how the controller's process ended and where the episode was into an
``Ending`` (``repository.trial``): ``success`` when the task was achieved, ``fail``
when the trial ran to its end without achieving it, ``error`` when something broke.
"""

from __future__ import annotations

import errno
import re
import signal
from collections.abc import Mapping

from repository.trial import Ending, Value
from repository.units import MiB
from sandbox.api import Exit, Limits
from sandbox.runtime import CODE
from scheduler.host import Episode

_FRAME = re.compile(r'^\s*File "(?P<file>[^"]+)", line (?P<line>\d+)(?:, in (?P<where>.+))?$')
# Node.js: "    at main (file:///code/x.mjs:3:7)" or "    at file:///code/x.mjs:3:7"
_NODE_FRAME = re.compile(
    r"^\s+at (?:(?P<where>.+?) \()?(?:file://)?(?P<file>/[^:()]+):(?P<line>\d+):\d+\)?$"
)
_NODE_EXIT = re.compile(r"^Node\.js v\d+")  # the last line Node prints of an uncaught error
_PYTHON_TRACEBACK = "Traceback (most recent call last):"
_INSTALLED = frozenset({"site-packages", "dist-packages", "node_modules"})


def judge(exit_: Exit, episode: Episode, *, ended: bool, limits: Limits) -> Ending:
    """The ending of a trial whose controller ended as ``exit_``.

    The episode's end wins over how the controller went: a controller stopped after
    the episode ended has done its part. A physics divergence is an error (the lab's
    model broke), not a failure of the controller at its task. A controller that exits
    with 0 having never stepped ran nothing: an error too. One that exits with 0 before
    the episode ended gave up: the task was not achieved, a fail.
    """
    at = f"at tick {episode.tick}"
    if episode.diverged:
        return Ending.error(
            f"{episode.reason}; the lab's simulation broke (report it, with the trial)"
        )
    if ended:
        return episode_ending(episode)
    if exit_.out_of_memory:
        return Ending.error(f"out of memory {at} (the limit is {limits.memory // MiB} MiB)")
    if exit_.output_exceeded:
        return Ending.error(
            f"the controller printed more than {limits.output // MiB} MiB {at}; it was stopped",
        )
    if exit_.wall_exceeded:
        return Ending.error(f"time limit: the controller ran for {limits.wall:g} s (stopped {at})")
    if exit_.cpu_exceeded:
        return Ending.error(f"CPU time limit of {limits.cpu_seconds} s reached {at}")
    if exit_.code == 0 and episode.tick == 0:
        return Ending.error("the controller exited with 0 before its first /lab/step: nothing ran")
    if exit_.code == 0:
        return Ending.fail(
            f"the controller exited with 0 {at}, before the episode ended; the task was not"
            " achieved"
        )
    if exit_.code is None:
        name = _signal_name(exit_.signal)
        return Ending.error(f"the controller was killed by {name} {at}")
    detail = crash_summary(exit_.stderr)
    return Ending.error(
        f"the controller exited with {exit_.code} {at}" + (f": {detail}" if detail else "")
    )


def episode_ending(episode: Episode) -> Ending:
    """The ending of a trial whose episode ended: success or fail, as the task says."""
    what = f"{episode.status}: {episode.reason}" if episode.reason else episode.status
    if episode.achieved:
        return Ending.success(f"the task was achieved at tick {episode.tick}: {episode.reason}")
    return Ending.fail(f"the episode ended at tick {episode.tick} without success: {what}")


def crash_summary(stderr: bytes) -> str:
    """The end of a crash's stderr: a Python traceback's error and its innermost frame
    in the controller's own files (else its innermost frame), Node.js's uncaught error
    and its first frame in the controller's own files (else outside Node itself), or
    else the last meaningful line.

    The controller's own frame, not the innermost: an error the client library (or
    NumPy, or roslibpy) raised on the controller's behalf, such as the lab refusing an
    ``/action``, is raised in the library's code, and the line to fix is the caller's.
    """
    lines = [line.rstrip() for line in stderr.decode("utf-8", "replace").splitlines()]
    lines = [line for line in lines if line.strip()]
    if not lines:
        return ""
    if _NODE_EXIT.match(lines[-1]):
        return _node_summary(lines[:-1])
    last = lines[-1].strip()[:300]
    # the last traceback: with chained exceptions, the one the controller died of
    start = max((i for i, line in enumerate(lines) if line == _PYTHON_TRACEBACK), default=0)
    frames = [match for match in map(_FRAME.match, lines[start:]) if match]
    if not frames:
        return last
    match = next((m for m in reversed(frames) if _own(m["file"])), frames[-1])
    where = f", in {match['where']}" if match["where"] else ""
    return f"{last} ({match['file']}, line {match['line']}{where})"


def _own(file: str) -> bool:
    """Whether ``file`` is of the controller's own code: in its repository (the
    sandbox's ``/code``), and not a package installed or vendored there."""
    return file.startswith(CODE + "/") and _INSTALLED.isdisjoint(file.split("/"))


def _node_summary(lines: list[str]) -> str:
    """Node's uncaught error: the line before its last stack, and the stack's first frame
    in the controller's own files, else its first outside Node itself."""
    end = max((i for i, line in enumerate(lines) if line.lstrip().startswith("at ")), default=-1)
    if end < 0:
        return lines[-1].strip()[:300] if lines else ""
    start = end
    while start > 0 and lines[start - 1].lstrip().startswith("at "):
        start -= 1
    message = lines[start - 1].strip()[:300] if start > 0 else ""
    frames = [match for match in map(_NODE_FRAME.match, lines[start : end + 1]) if match]
    if not frames:
        return message
    match = next((m for m in frames if _own(m["file"])), frames[0])
    where = f", in {match['where']}" if match["where"] else ""
    return f"{message} ({match['file']}, line {match['line']}{where})"


def _signal_name(number: int | None) -> str:
    if number is None:
        return "a signal"
    try:
        return signal.Signals(number).name
    except ValueError:
        return f"signal {number}"


def storage_failure(err: OSError, what: str) -> str:
    """``what`` went wrong (a clause: "the record could not be stored"), with the cause,
    saying so first when it is that the lab's disk is full: the operator's to fix."""
    detail = err.strerror or str(err)
    if err.filename:
        detail += f": {err.filename}"
    lead = "the lab's disk is full: " if err.errno in (errno.ENOSPC, errno.EDQUOT) else ""
    return f"{lead}{what} ({detail})"


def judge_leg(
    episode: Episode, goals: Mapping[str, int], forfeits: Mapping[str, str]
) -> tuple[Ending, dict[str, Value]]:
    """The ending of a leg of a match, and its result for the record's metrics.

    ``goals`` are each side's (in the task's order of sides), ``forfeits`` the sides
    that forfeited and why ("sent no /lab/step within 10 s of tick 40"). A leg with a
    result is a ``success`` whoever won it: the leg was played. The result:
    ``winner`` (a side, or ``draw``), ``ended_by`` (``goal``, ``time`` or
    ``forfeit``) and ``forfeited`` (the sides that did, comma-separated; "" for none).
    Every side forfeiting, or the physics breaking, leaves no result: an error.
    """
    sides = list(goals)
    score = "-".join(str(goals[side]) for side in sides)
    forfeited = ",".join(side for side in sides if side in forfeits)
    if episode.diverged:
        return Ending.error(
            f"{episode.reason}; the lab's simulation broke (report it, with the trial)"
        ), {}
    if forfeits:
        why = "; ".join(f"{side} {forfeits[side]}" for side in sides if side in forfeits)
        result: dict[str, Value] = {"ended_by": "forfeit", "forfeited": forfeited}
        standing = [side for side in sides if side not in forfeits]
        if not standing:
            return Ending.error(f"no result, every side forfeited: {why}"), {
                **result,
                "winner": "",
            }
        winner = standing[0] if len(standing) == 1 else "draw"
        said = f"{winner} wins by forfeit" if winner != "draw" else "a draw by forfeit"
        return Ending.success(f"{said} at tick {episode.tick}: {why}"), {
            **result,
            "winner": winner,
        }
    top = max(goals.values())
    leaders = [side for side in sides if goals[side] == top]
    winner = leaders[0] if len(leaders) == 1 else "draw"
    ended_by = "goal" if sum(goals.values()) else "time"
    said = f"{winner} won {score}" if winner != "draw" else f"a draw, {score},"
    end = f" ({episode.reason})" if episode.reason else ""
    return Ending.success(f"{said} at tick {episode.tick}{end}"), {
        "winner": winner,
        "ended_by": ended_by,
        "forfeited": "",
    }
