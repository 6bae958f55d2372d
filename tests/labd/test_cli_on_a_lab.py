"""The ``labd`` commands that talk to a lab, run in process (``labd.cli.main``) against
a real lab on 127.0.0.1 (its HTTP API, no workers): trials and episodes are claimed and
filed here as a worker files them, so each ending a command must report is made on
purpose. A command that waits runs on a thread while the test files what it waits for."""

from __future__ import annotations

import json
import threading
from collections.abc import Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Any

import pytest

from labd.api.models import EvaluationView
from labd.cli import main
from labd.commands import evaluate
from labd.commands.common import ExitCode
from repository.trial import Claim, Filing
from scheduler.client import ApiClient
from scheduler.fetch import FetchPolicy
from tests.fakes import verify_episodes
from tests.helpers.githttp import GitRepo
from tests.helpers.labs import lab_config, running

LAB_TOML = '[controller]\ncommand = ["python", "c.py"]\ntask = "icreate-maze"\n'
DEV, TEST = 20, 50  # the maze's suites' episodes
WAIT = 60.0  # seconds a test waits for what the command or the lab does


@pytest.fixture
def server(tmp_path, monkeypatch) -> Iterator[Any]:
    """A lab without workers that takes local repositories; the commands find it (and
    alice's token) in the environment, as a user's shell gives them."""
    fetch = FetchPolicy(schemes=frozenset({"file"}))
    with running(lab_config(tmp_path / "data", robots=(), service={"fetch": fetch})) as server:
        service = server.lab.service
        service.queue.check = None  # the filings here name no record file
        monkeypatch.setenv("LABD_SERVER", server.http_url())
        monkeypatch.setenv("LABD_TOKEN", service.index.add_user("alice", max_daily=500))
        yield server


@pytest.fixture
def repo(tmp_path) -> Path:
    return GitRepo.create(tmp_path / "ctl", {"lab.toml": LAB_TOML, "c.py": "pass\n"}).path


def run(capsys, *argv: str) -> tuple[int, str, str]:
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def claims(service: Any, count: int, command: Future[int] | None = None) -> Iterator[Claim]:
    """The next ``count`` queued trials, claimed as a worker claims them, as soon as they
    are queued (a ``command`` that has ended queues no more: then no more are awaited)."""
    deadline = threading.Event()
    timer = threading.Timer(WAIT, deadline.set)
    timer.start()
    try:
        for _ in range(count):
            while (claim := service.queue.claim("w")) is None:
                if command is not None and command.done():
                    return
                assert not deadline.wait(0.02), f"no trial was queued within {WAIT} s"
            yield claim
    finally:
        timer.cancel()


def file(service: Any, claim: Claim, outcome: str | None, **more: Any) -> None:
    """File ``claim`` as a worker would: finished with ``outcome`` (None: cancelled),
    its replay verified beforehand (so no command waits for a verdict)."""
    verify_episodes(service, [claim.id])
    if outcome is None:
        filing = Filing(status="cancelled", reason="stopped")
    else:
        filing = Filing(
            status="finished",
            outcome=outcome,
            reason=more.pop("reason", f"{outcome} at tick 9"),
            data_digest=f"{claim.id:064x}",
            metrics={"reward": 1.0 if outcome == "success" else 0.0},
            **more,
        )
    assert service.queue.finish(claim.id, "w", filing)


def file_suite(service: Any, successes: int, episodes: int = DEV, **fault: Any) -> None:
    """Claim and file every episode of an evaluation: the first ``successes`` succeed,
    the rest fail; ``fault`` (``lab_fault=True``) makes the last one the lab's error."""
    for n, claim in enumerate(claims(service, episodes)):
        if fault and n == episodes - 1:
            file(service, claim, "error", reason="the worker was lost", **fault)
        else:
            file(service, claim, "success" if n < successes else "fail")


def in_background(*argv: str) -> tuple[ThreadPoolExecutor, Future[int]]:
    pool = ThreadPoolExecutor(1)
    return pool, pool.submit(main, list(argv))


def test_min_success_without_wait_waits_and_a_failed_gate_says_so(server, repo, capsys):
    """``labd evaluate --min-success 90%`` without ``--wait`` waits for every episode
    (saying so once), and a gate that fails exits 1 with one line saying it failed: a
    user's CI that forgot ``--wait`` is not green for a score it never checked."""
    service = server.lab.service
    pool, command = in_background("evaluate", str(repo), "--min-success", "90%")
    with pool:
        for n, claim in enumerate(claims(service, DEV, command)):
            file(service, claim, "success" if n < 9 else "fail")
        code = command.result(WAIT)
    out, err = capsys.readouterr()
    assert code == ExitCode.FAIL, out + err
    assert err.count("--min-success waits for every episode, as --wait does") == 1, err
    assert "gate failed: 45 % is below --min-success 90 % (evaluation 1:" in err, err
    assert "success rate 45 %" in out


@pytest.mark.parametrize(
    ("case", "code", "said"),
    [
        pytest.param(
            "passed",
            ExitCode.SUCCESS,
            "gate passed: 85 % ≥ 80 % (evaluation 1: 17 of 20 episodes succeeded)",
            id="passed",
        ),
        pytest.param(
            "failed",
            ExitCode.FAIL,
            "gate failed: 45 % is below --min-success 80 % (evaluation 1: 9 of 20 episodes"
            " succeeded)",
            id="failed",
        ),
        pytest.param(
            "cancelled",
            ExitCode.CANCELLED,
            "gate not checked: evaluation 1 was cancelled by its submitter (17 episodes"
            " unfinished)",
            id="cancelled",
        ),
        pytest.param(
            "partial",
            ExitCode.ERROR,
            "gate not checked: evaluation 1 is partial: the lab broke 1 episode (episode 19),"
            " not the controller; evaluate again",
            id="partial",
        ),
        pytest.param(
            "held out",
            ExitCode.SUCCESS,
            "gate passed: 80 % ≥ 80 % (evaluation 1, held out: 40 of 50 episodes succeeded)",
            id="held-out",
        ),
    ],
)
def test_every_gate_outcome_says_itself_in_one_line(server, repo, capsys, case, code, said):
    """Each way an evaluation can end gives its exit code and one line that says why:
    passed, failed, cancelled, partial (the lab broke an episode), and a held-out
    evaluation, whose score is hidden until it has ended, gated once it has."""
    service = server.lab.service
    suite = "test" if case == "held out" else "dev"
    done, _, err = run(capsys, "evaluate", str(repo), "--suite", suite)
    assert done == 0, err
    if case == "passed":
        file_suite(service, 17)
    elif case == "failed":
        file_suite(service, 9)
    elif case == "cancelled":
        for claim in claims(service, 3):
            file(service, claim, "success")
        assert run(capsys, "cancel", "--evaluation", "1")[0] == 0
    elif case == "partial":
        file_suite(service, 10, lab_fault=True)
    else:
        file_suite(service, 40, TEST)
    with ApiClient(server.http_url()) as client:
        evaluation = client.get("/api/evaluations/1", EvaluationView)
    assert evaluate.gate(evaluation, 0.8) == (code, said)


@pytest.mark.parametrize(
    ("rate", "bound", "said"),
    [
        (0.85, 0.8, ("85 %", "80 %")),
        (0.85, 0.849, ("85.0 %", "84.9 %")),
        (0.8, 0.8, ("80 %", "80 %")),
        (0.3, 1 / 3, ("30 %", "33 %")),
        (0.3334, 1 / 3, ("33.34 %", "33.33 %")),
    ],
)
def test_a_rate_and_its_gate_never_print_alike_unless_they_are(rate, bound, said):
    """The gate's line never reads "80 % is below --min-success 80 %"."""
    assert evaluate._percents(rate, bound) == said


def test_waiting_without_a_gate_says_nothing_more_of_a_whole_evaluation(server, repo, capsys):
    """``--wait`` alone gates nothing: a finished evaluation exits 0 with no gate line,
    while a cancelled one still says why it exits 4."""
    service = server.lab.service
    run(capsys, "evaluate", str(repo))
    file_suite(service, 2)
    run(capsys, "evaluate", str(repo))
    assert run(capsys, "cancel", "--evaluation", "2")[0] == 0
    with ApiClient(server.http_url()) as client:
        whole = client.get("/api/evaluations/1", EvaluationView)
        cancelled = client.get("/api/evaluations/2", EvaluationView)
    assert evaluate.gate(whole, None) == (ExitCode.SUCCESS, None)
    assert evaluate.gate(cancelled, None) == (
        ExitCode.CANCELLED,
        "evaluation 2 was cancelled by its submitter (20 episodes unfinished)",
    )


def test_a_reward_without_an_interval_says_why(server, repo, capsys):
    """Rewards all alike give no 95 % interval (``repository.stats.mean_interval``): the
    result says the mean alone, and why, rather than a zero-width interval."""
    service = server.lab.service
    run(capsys, "evaluate", str(repo))
    file_suite(service, DEV)  # every episode a success of reward 1
    with ApiClient(server.http_url()) as client:
        alike = client.get("/api/evaluations/1", EvaluationView)
    assert (alike.mean_reward, alike.reward_interval) == (1.0, None)
    said = "\n".join(evaluate._lines(alike))
    assert "  mean reward 1 (no 95 % interval: the rewards are all alike, or fewer than 6)" in said


def test_cancel_an_evaluation_from_the_command_line(server, repo, capsys):
    """``labd cancel --evaluation ID`` cancels an evaluation's episodes that have not
    ended and says so; again, it exits 2 saying there was nothing left to cancel; an
    episode cancelled alone is refused with the command that cancels its evaluation."""
    service = server.lab.service
    run(capsys, "evaluate", str(repo))
    [first] = claims(service, 1)
    file(service, first, "success")
    code, _, err = run(capsys, "cancel", str(first.id + 1))
    assert code == 2
    assert f"trial {first.id + 1} is an episode of evaluation 1" in err
    assert "labd cancel --evaluation 1" in err
    code, out, err = run(capsys, "cancel", "--evaluation", "1")
    assert code == 0, err
    assert out.splitlines()[0] == (
        "evaluation 1 cancelled by its submitter (19 episodes unfinished)"
    )
    code, out, err = run(capsys, "cancel", "--evaluation", "1", "--json")
    assert code == 2
    assert json.loads(out) == {
        "error": "evaluation 1 had already ended (cancelled); nothing to cancel"
    }
    assert service.evaluations.get(1).status == "cancelled"


def test_a_rerun_that_erred_says_its_outcome_and_reason(server, repo, capsys):
    """``labd rerun TRIAL --wait`` on a rerun that broke says how it ended and why, not
    only that it made no record, and exits 5: it did not reproduce its original."""
    service = server.lab.service
    code, _, err = run(capsys, "submit", str(repo))
    assert code == 0, err
    [original] = claims(service, 1)
    file(service, original, "success", mcap=f"sha256:{0:064x}")
    pool, command = in_background("rerun", str(original.id), "--wait")
    with pool:
        for claim in claims(service, 1, command):
            file(
                service,
                claim,
                "error",
                reason="the controller exited with code 1 at tick 0: ZeroDivisionError",
                reproduced=False,
                divergence="the rerun made no record",
            )
        code = command.result(WAIT)
    out, err = capsys.readouterr()
    assert code == ExitCode.DIVERGED, out + err  # it did not reproduce its original
    assert out.splitlines()[-1] == (
        f"trial {original.id + 1} (rerun of {original.id}): the rerun made no record; it"
        " ended ERROR: the controller exited with code 1 at tick 0: ZeroDivisionError"
    )


def test_labd_tasks_lists_the_benchmarks_after_the_tasks(server, capsys):
    """``labd tasks`` ends with the benchmarks (name, how many tasks, doc), asked of the
    lab or (``--local``) of this machine's plugins; ``--json`` adds them as ``benchmarks``,
    the list ``GET /api/benchmarks`` answers."""
    code, out, _ = run(capsys, "tasks")
    assert code == ExitCode.SUCCESS
    tasks, _, benchmarks = out.partition("\nbenchmarks (")
    assert "dmc-cartpole-balance (version" in tasks and "dmc-classic" not in tasks
    assert "\ndmc-classic (6 tasks)\n  Six classic tasks of the DeepMind Control Suite" in (
        benchmarks
    )
    assert "\ndmc (26 tasks)\n  All 26 tasks of the dm_control suite pack" in benchmarks
    for argv in (("tasks", "--json"), ("tasks", "--local", "--json")):
        code, out, _ = run(capsys, *argv)
        listing = json.loads(out)
        assert code == ExitCode.SUCCESS and set(listing) == {"tasks", "problems", "benchmarks"}
        by_name = {b["name"]: b for b in listing["benchmarks"]}
        assert [t["task"] for t in by_name["dmc-classic"]["tasks"]][:2] == [
            "dmc-cartpole-balance",
            "dmc-cartpole-swingup",
        ]
        assert len(by_name["dmc"]["tasks"]) == 26
