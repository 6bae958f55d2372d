"""A trial's ending in a sentence, from how the controller and the episode ended."""

from __future__ import annotations

import pytest

from repository.digests import manifest_digest as digest
from repository.trial import EpisodeStatus, Outcome, Status
from sandbox.api import Exit, Limits
from scheduler.host import Episode
from scheduler.outcome import crash_summary, judge, judge_leg

MID = Episode(tick=3, running=True, status="running", reason="", achieved=False, diverged=False)
TRACEBACK = b"""Traceback (most recent call last):
  File "/code/controller.py", line 88, in <module>
    main()
  File "/code/controller.py", line 42, in main
    import foo
ModuleNotFoundError: No module named 'foo'
"""


@pytest.mark.parametrize(
    ("exit_", "outcome", "reason"),
    [
        (
            Exit(0),
            Outcome.FAIL,
            "the controller exited with 0 at tick 3, before the episode ended",
        ),
        (
            Exit(1, stderr=TRACEBACK),
            Outcome.ERROR,
            "the controller exited with 1 at tick 3: ModuleNotFoundError: No module named"
            " 'foo' (/code/controller.py, line 42, in main)",
        ),
        (Exit(None, signal=9), Outcome.ERROR, "the controller was killed by SIGKILL at tick 3"),
        (
            Exit(None, signal=9, out_of_memory=True),
            Outcome.ERROR,
            "out of memory at tick 3 (the limit is",
        ),
        (
            Exit(None, signal=9, output_exceeded=True),
            Outcome.ERROR,
            "the controller printed more than 8 MiB",
        ),
        (
            Exit(None, signal=9, wall_exceeded=True),
            Outcome.ERROR,
            "time limit: the controller ran for",
        ),
        (Exit(None, signal=24, cpu_exceeded=True), Outcome.ERROR, "CPU time limit of 3600 s"),
    ],
)
def test_how_the_controller_ended(exit_, outcome, reason):
    """Each way a controller ends gives its outcome and a sentence saying why."""
    ending = judge(exit_, MID, ended=False, limits=Limits())
    assert ending.status is Status.FINISHED
    assert ending.outcome is outcome
    assert ending.reason.startswith(reason), ending.reason


def test_exiting_before_the_first_step_is_an_error():
    """A controller that exits with 0 having never stepped ran nothing: an error."""
    start = Episode(0, True, "running", "", achieved=False, diverged=False)
    ending = judge(Exit(0), start, ended=False, limits=Limits())
    assert ending.outcome is Outcome.ERROR and "nothing ran" in ending.reason


@pytest.mark.parametrize(
    ("status", "achieved", "outcome", "words"),
    [
        ("succeeded", True, Outcome.SUCCESS, "the task was achieved at tick 3: reached the goal"),
        ("truncated", False, Outcome.FAIL, "without success: truncated: reached the goal"),
        ("failed", False, Outcome.FAIL, "without success: failed: reached the goal"),
    ],
)
def test_the_episode_end_wins_and_says_whether_the_task_was_achieved(
    status, achieved, outcome, words
):
    """A controller stopped after its episode ended has done its part: the task decides."""
    over = Episode(3, False, status, "reached the goal", achieved=achieved, diverged=False)
    ending = judge(Exit(None, signal=15), over, ended=True, limits=Limits())
    assert ending.outcome is outcome
    assert words in ending.reason


def test_divergence_is_an_error():
    """A diverging physics is an error of the lab, not a failure at the task."""
    blown = Episode(1, False, "failed", "the physics diverged at tick 1", False, diverged=True)
    ending = judge(Exit(0), blown, ended=True, limits=Limits())
    assert ending.outcome is Outcome.ERROR and "physics diverged" in ending.reason


def test_a_crash_summary_names_the_last_frame():
    """The summary of a traceback is its error line and the innermost file and line."""
    assert crash_summary(TRACEBACK).endswith("(/code/controller.py, line 42, in main)")
    assert crash_summary(b"segfault\n\n") == "segfault"
    assert crash_summary(b"") == ""


NODE_CRASH = b"""file:///code/lib/plan.mjs:12
    throw new RangeError("no way to the goal");
    ^

RangeError: no way to the goal
    at plan (file:///code/lib/plan.mjs:12:11)
    at file:///code/controller.mjs:40:3
    at process.processTicksAndRejections (node:internal/process/task_queues:95:5)

Node.js v20.20.2
"""
NODE_MISSING = b"""node:internal/modules/esm/resolve:853
  throw new ERR_MODULE_NOT_FOUND(packageName, fileURLToPath(base), null);
        ^

Error [ERR_MODULE_NOT_FOUND]: Cannot find package 'three' imported from /code/controller.mjs
    at packageResolve (node:internal/modules/esm/resolve:853:9)
    at moduleResolve (node:internal/modules/esm/resolve:910:20) {
  code: 'ERR_MODULE_NOT_FOUND'
}

Node.js v20.20.2
"""


def test_a_node_crash_summary_names_its_error_and_the_controllers_frame():
    """Node's uncaught error: its error line and the first frame in the controller's own
    files; an error raised inside Node itself: its error line alone."""
    assert crash_summary(NODE_CRASH) == (
        "RangeError: no way to the goal (/code/lib/plan.mjs, line 12, in plan)"
    )
    assert crash_summary(NODE_MISSING) == (
        "Error [ERR_MODULE_NOT_FOUND]: Cannot find package 'three' imported from"
        " /code/controller.mjs"
    )
    assert crash_summary(b"something odd\n\nNode.js v20.20.2\n") == "something odd"


def test_manifest_digest_is_canonical():
    """Key order does not change the digest; any value does."""
    assert digest({"a": 1, "b": [1, 2]}) == digest({"b": [1, 2], "a": 1})
    assert digest({"a": 1}) != digest({"a": 2})


EPISODE = Episode(40, False, EpisodeStatus.SUCCEEDED, "home scored", achieved=True, diverged=False)


def test_a_leg_is_won_by_goals_or_drawn_at_the_time_limit():
    ending, result = judge_leg(EPISODE, {"home": 1, "away": 0}, {})
    assert (ending.outcome, result) == (
        Outcome.SUCCESS, {"winner": "home", "ended_by": "goal", "forfeited": ""}
    )  # fmt: skip
    assert ending.reason == "home won 1-0 at tick 40 (home scored)"
    timed = Episode(1800, False, EpisodeStatus.FAILED, "no goal in 45 s", False, False)
    ending, result = judge_leg(timed, {"home": 0, "away": 0}, {})
    assert result == {"winner": "draw", "ended_by": "time", "forfeited": ""}
    assert ending.outcome is Outcome.SUCCESS and ending.reason.startswith("a draw, 0-0, at tick")


def test_a_side_that_forfeits_loses_and_every_side_forfeiting_is_no_result():
    running = Episode(12, True, EpisodeStatus.RUNNING, "", achieved=False, diverged=False)
    late = {"away": "sent no /lab/step within 10 s of tick 12"}
    ending, result = judge_leg(running, {"home": 0, "away": 0}, late)
    assert result == {"winner": "home", "ended_by": "forfeit", "forfeited": "away"}
    assert ending.reason == (
        "home wins by forfeit at tick 12: away sent no /lab/step within 10 s of tick 12"
    )
    both = {"home": "its controller exited with 1", "away": "sent no /lab/step"}
    ending, result = judge_leg(running, {"home": 0, "away": 0}, both)
    assert ending.outcome is Outcome.ERROR and result["winner"] == ""
    assert ending.reason.startswith("no result, every side forfeited: home its controller")
    broke = Episode(3, False, EpisodeStatus.FAILED, "the physics diverged", False, diverged=True)
    ending, result = judge_leg(broke, {"home": 0, "away": 0}, {})
    assert ending.outcome is Outcome.ERROR and result == {}
