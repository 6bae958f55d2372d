"""``labd evaluate --benchmark`` run in process (``labd.cli.main``) against a real lab on
127.0.0.1 (its HTTP API, no workers): the run's episodes are claimed and filed here as a
worker files them, their replays verified beforehand, so each ending the command must
report is made on purpose. A command that waits runs on a thread while the test files
what it waits for, and looks at the run every few milliseconds rather than seconds."""

from __future__ import annotations

import json
import re
import threading
from collections.abc import Iterator
from typing import Any

import pytest

from labd.api.models import EvaluationView
from labd.commands import evaluate
from labd.commands.common import ExitCode
from repository.trial import Claim, Filing
from scheduler.client import ApiClient
from scheduler.fetch import FetchPolicy
from tests.fakes import verify_episodes
from tests.helpers.githttp import GitRepo
from tests.helpers.labs import lab_config, running
from tests.labd.test_cli_on_a_lab import WAIT, claims, in_background, run

LAB_TOML = '[controller]\ncommand = ["python", "c.py"]\ntask = "dmc-cartpole-balance"\n'
TASKS = [
    "dmc-cartpole-balance", "dmc-cartpole-swingup", "dmc-pendulum-swingup",
    "dmc-reacher-easy", "dmc-point_mass-easy", "dmc-ball_in_cup-catch",
]  # fmt: skip
DEV = 20  # episodes of each task's dev suite
EPISODES = len(TASKS) * DEV
POLL = 0.02  # seconds between the waiting command's looks at the run, here


@pytest.fixture
def server(tmp_path, monkeypatch) -> Iterator[Any]:
    """A lab without workers that takes local repositories; alice's daily limit takes a
    run of dmc-classic (120 episodes)."""
    fetch = FetchPolicy(schemes=frozenset({"file"}))
    monkeypatch.setattr(evaluate, "POLL", POLL)
    with running(lab_config(tmp_path / "data", robots=(), service={"fetch": fetch})) as server:
        service = server.lab.service
        service.queue.check = None  # the filings here name no record file
        monkeypatch.setenv("LABD_SERVER", server.http_url())
        monkeypatch.setenv("LABD_TOKEN", service.index.add_user("alice", max_daily=500))
        yield server


@pytest.fixture
def repo(tmp_path) -> GitRepo:
    return GitRepo.create(tmp_path / "ctl", {"lab.toml": LAB_TOML, "c.py": "pass\n"})


def file(service: Any, claim: Claim, reward: float) -> None:
    """File ``claim`` finished with a return of ``reward`` (0 to 1000), verified."""
    verify_episodes(service, [claim.id])
    filing = Filing(
        status="finished",
        outcome="success" if reward >= 900 else "fail",
        reason=f"a return of {reward}",
        data_digest=f"{claim.id:064x}",
        metrics={"reward": reward},
    )
    assert service.queue.finish(claim.id, "w", filing)


def reward(claim: Claim, scale: float) -> float:
    return float((claim.id * 389) % 1000) * scale


def test_a_benchmark_run_is_queued_and_printed_without_waiting(server, repo, capsys):
    """``labd evaluate REPO --benchmark dmc-classic`` queues every task's evaluation,
    says so in one line on stderr and exits 0 at once; ``--json`` prints the run as the
    API serves it."""
    code, out, err = run(capsys, "evaluate", str(repo.path), "--benchmark", "dmc-classic")
    assert code == ExitCode.SUCCESS, err
    commit = repo.rev()
    assert err.startswith(
        f"benchmark run 1: {repo.path}@{commit[:12]} on dmc-classic, 6 tasks,"
        f" {EPISODES} episodes queued; http://"
    ), err
    lines = out.splitlines()
    assert lines[0].endswith(": queued")
    assert [line.split()[0] for line in lines[1:7]] == TASKS
    assert "  no IQM yet (0 of 120 episodes ended; one of each task needed)" in lines
    code, out, _ = run(capsys, "evaluate", str(repo.path), "--benchmark", "dmc-classic", "--json")
    assert code == ExitCode.SUCCESS
    made = json.loads(out)
    assert (made["id"], made["commit"], made["episodes"]) == (2, commit, EPISODES)
    assert [t["task"] for t in made["evaluations"]] == TASKS
    assert made["url"].endswith("/api/benchmark-runs/2")


def test_waiting_follows_the_run_to_its_end_and_prints_each_task_and_the_iqm(
    server, repo, capsys, monkeypatch
):
    """``--wait`` prints a progress line when the run moves (the IQM so far once every
    task has an ended episode), then one line per task and the IQM, mean and median with
    their intervals, verified and signed, as the API has them; exit 0."""
    service = server.lab.service
    seen = threading.Event()
    progress = evaluate._run_progress

    def watched(*args: Any) -> str:
        line = progress(*args)
        if line.endswith("so far"):
            seen.set()
        return line

    monkeypatch.setattr(evaluate, "_run_progress", watched)
    pool, command = in_background(
        "evaluate", str(repo.path), "--benchmark", "dmc-classic", "--wait"
    )
    with pool:
        tasks: set[str | None] = set()
        for claim in claims(service, EPISODES, command):
            file(service, claim, reward(claim, 1.0))
            tasks.add(claim.order.task)
            if len(tasks) == len(TASKS) and not seen.is_set():  # the run has an IQM now
                assert seen.wait(WAIT), "no progress line with the IQM so far"
        code = command.result(WAIT)
    out, err = capsys.readouterr()
    assert code == ExitCode.SUCCESS, out + err
    assert re.search(r"benchmark run 1: \d+/120 episodes done; IQM 0\.\d{3} so far\n", err), err
    with ApiClient(server.http_url()) as client:
        done = client.get("/api/benchmark-runs/1", evaluate.RunView)
    assert (done.status, done.done, done.verified, done.suite) == ("finished", EPISODES, True, "")
    assert done.iqm is not None and done.iqm_interval is not None
    assert err.rstrip().endswith(f"benchmark run 1: 120/120 episodes done; IQM {done.iqm:.3f}")
    lines = out.splitlines()
    assert lines[0] == (f"benchmark run 1: {repo.path}@{repo.rev()[:12]} on dmc-classic: finished")
    for line, task in zip(lines[1:7], done.evaluations, strict=True):
        assert task.normalized_mean is not None and task.normalized_interval is not None
        low, high = task.normalized_interval
        assert line.split() == [
            task.task, f"{task.normalized_mean:.3f}", "(95", "%", "interval", f"{low:.3f}",
            "to", f"{high:.3f})", "over", "20", "of", "20", "episodes", "(evaluation",
            f"{task.evaluation},", "finished)",
        ]  # fmt: skip
    low, high = done.iqm_interval
    assert lines[7].startswith(
        f"  IQM {done.iqm:.3f} (95 % interval {low:.3f} to {high:.3f}), mean {done.mean:.3f}"
    )
    assert f", median {done.median:.3f} (95 % interval" in lines[7]
    assert "  verified: the lab's replay of every episode of every task reproduced its record" in (
        lines
    )
    assert lines[-1] == f"  {done.url}"
    assert "gate" not in err  # --wait alone gates nothing


def test_a_failed_iqm_gate_waits_and_exits_1_saying_so(server, repo, capsys):
    """``--min-iqm 0.5`` without ``--wait`` waits for every episode (saying so once) and,
    the IQM below 0.5, exits 1 with one line saying the gate failed."""
    service = server.lab.service
    pool, command = in_background(
        "evaluate", str(repo.path), "--benchmark", "dmc-classic", "--min-iqm", "0.5"
    )
    with pool:
        for claim in claims(service, EPISODES, command):
            file(service, claim, reward(claim, 0.3))
        code = command.result(WAIT)
    out, err = capsys.readouterr()
    assert code == ExitCode.FAIL, out + err
    assert err.count("--min-iqm waits for every episode, as --wait does") == 1, err
    with ApiClient(server.http_url()) as client:
        done = client.get("/api/benchmark-runs/1", evaluate.RunView)
    assert done.iqm is not None and done.iqm < 0.5
    assert err.splitlines()[-1] == (
        f"gate failed: IQM {done.iqm:.3f} is below --min-iqm 0.500 (benchmark run 1 on"
        " dmc-classic: 120 episodes)"
    )


def test_a_run_with_a_cancelled_evaluation_exits_as_that_evaluation(server, repo, capsys):
    """A run one of whose evaluations was cancelled has no whole score: its gate is not
    checked and it exits 4 naming that evaluation, as ``labd evaluate`` would."""
    service = server.lab.service
    code, _, err = run(capsys, "evaluate", str(repo.path), "--benchmark", "dmc-classic")
    assert code == ExitCode.SUCCESS, err
    assert run(capsys, "cancel", "--evaluation", "1")[0] == ExitCode.SUCCESS
    for claim in claims(service, EPISODES - DEV):
        file(service, claim, reward(claim, 1.0))
    with ApiClient(server.http_url()) as client:
        done = client.get("/api/benchmark-runs/1", evaluate.RunView)
        views = [
            client.get(f"/api/evaluations/{t.evaluation}", EvaluationView) for t in done.evaluations
        ]
    assert done.status == "cancelled"
    assert evaluate.run_gate(done, views, 0.5) == (
        ExitCode.CANCELLED,
        "gate not checked: benchmark run 1: evaluation 1 was cancelled by its submitter"
        " (20 episodes unfinished)",
    )


@pytest.mark.parametrize(
    ("argv", "said"),
    [
        pytest.param(
            ("--task", "dmc-cartpole-balance"),
            "--benchmark and --task are exclusive: a benchmark names its own tasks",
            id="task",
        ),
        pytest.param(
            ("--min-success", "80%"),
            "--min-success gates one evaluation; a benchmark run's gate is --min-iqm",
            id="min-success",
        ),
    ],
)
def test_options_of_one_evaluation_are_usage_errors_with_a_benchmark(
    server, repo, capsys, argv, said
):
    """``--task`` or ``--min-success`` beside ``--benchmark`` exits 2 naming both options,
    and nothing is queued."""
    code, _, err = run(capsys, "evaluate", str(repo.path), "--benchmark", "dmc-classic", *argv)
    assert code == ExitCode.USAGE
    assert err == f"labd evaluate: {said}\n"
    assert server.lab.service.queue.claim("w") is None


def test_min_iqm_without_a_benchmark_is_a_usage_error(server, repo, capsys):
    """``--min-iqm`` gates a benchmark run only: without ``--benchmark`` it exits 2."""
    code, _, err = run(capsys, "evaluate", str(repo.path), "--min-iqm", "0.5")
    assert code == ExitCode.USAGE
    assert "--min-iqm gates a benchmark run: it needs --benchmark" in err


def test_an_unknown_benchmark_is_the_labs_refusal(server, repo, capsys):
    """A benchmark the lab does not have is refused by the lab (exit 2), with its
    reason, the nearest name; ``--json`` says it as ``{"error": ...}``."""
    code, _, err = run(capsys, "evaluate", str(repo.path), "--benchmark", "dmc-clasic")
    assert code == ExitCode.USAGE
    assert err.startswith("labd evaluate: ") and "did you mean dmc-classic" in err, err
    code, out, _ = run(capsys, "evaluate", str(repo.path), "--benchmark", "dmc-clasic", "--json")
    assert code == ExitCode.USAGE and "did you mean dmc-classic" in json.loads(out)["error"]
    assert server.lab.service.queue.claim("w") is None
