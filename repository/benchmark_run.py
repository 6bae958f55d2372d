"""A benchmark run: one commit evaluated on every task of a benchmark, and what that
adds up to, computed as rliable defines it (``repository.benchmark_stats``).

A run is one evaluation per task of the benchmark (``repository.evaluation``: each
pinned, replayed and signed as any other), queued together. What the run says is read
from those evaluations whenever it is asked for, so it is never out of step with them:

- per task: its evaluation, how many of its episodes ended, and the mean of their
  normalized scores (``repository.benchmark.normalized``) with its interval;
- over every ended episode of every task: the interquartile mean (IQM), the mean and
  the median, each with its 95 % stratified bootstrap interval, and the performance
  profile (the fraction of episodes scoring above each threshold);
- ``verified`` once every evaluation is verified (every episode replayed identically).

The leaderboard (``leaderboard``) ranks each commit by its first run of a benchmark and
suite, never by its best: rerunning until lucky buys nothing, and a run its submitter
cancelled stands as the commit's row, unranked.

The statistics are computed over the episodes that have ended, so a run's numbers move
while it runs and settle when its last episode ends; its ``status`` says which. Its
bootstrap is seeded by the run's id: the same run always shows the same intervals.
"""

from __future__ import annotations

import datetime as dt
from collections.abc import Sequence
from typing import Any

from pydantic import BaseModel, ConfigDict, Field

from repository.benchmark import Benchmark, BenchmarkTask, normalized
from repository.benchmark_stats import (
    Aggregate,
    aggregate,
    probability_of_improvement,
    profile,
)
from repository.evaluation import Evaluation
from repository.stats import Interval
from repository.trial import Status

BENCHMARK_RUN = "labd.benchmark-run/1"  # the schema of a run's signed statement


class TaskScore(BaseModel):
    """One task of a run: its evaluation and its episodes' normalized scores."""

    model_config = ConfigDict(frozen=True)

    task: str
    suite: str
    evaluation: int
    status: Status
    episodes: int = Field(description="the suite's episodes")
    done: int = Field(description="episodes ended (any outcome)")
    normalized_mean: float | None = Field(description="the mean normalized score so far")
    normalized_interval: tuple[float, float] | None = Field(
        default=None, description="its 95 % bootstrap interval"
    )
    verified: bool


class BenchmarkRun(BaseModel):
    """A run as the API serves it (``GET /api/benchmark-runs/{id}``)."""

    model_config = ConfigDict(frozen=True)

    id: int
    benchmark: str
    suite: str
    repository: str
    ref: str | None
    commit: str
    submitter: str
    status: Status
    created: dt.datetime
    finished: dt.datetime | None
    evaluations: list[TaskScore]
    episodes: int = Field(description="every task's episodes")
    done: int = Field(description="episodes ended so far")
    iqm: float | None = None
    iqm_interval: tuple[float, float] | None = None
    mean: float | None = None
    mean_interval: tuple[float, float] | None = None
    median: float | None = None
    median_interval: tuple[float, float] | None = None
    profile: list[tuple[float, float]] = Field(
        default_factory=list, description="(τ, fraction of episodes scoring above τ)"
    )
    verified: bool = Field(description="every task's evaluation verified")
    signature: dict[str, Any] | None = None


class Compared(BaseModel):
    """Two runs of one benchmark and suite (``GET /api/benchmark-runs/compare``)."""

    model_config = ConfigDict(frozen=True)

    a: int
    b: int
    benchmark: str
    probability_of_improvement: float = Field(
        description="the mean over tasks of P(an episode of A scores above one of B), ties half"
    )
    interval: tuple[float, float] = Field(description="its 95 % stratified bootstrap interval")
    tasks: int


def scores_of(task: BenchmarkTask, evaluation: Evaluation) -> list[float]:
    """The normalized scores of the evaluation's ended episodes (cancelled ones left out)."""
    return [normalized(task, row) for row in evaluation.rows if row.outcome is not None]


def run_of(
    row: Any, benchmark: Benchmark, evaluations: Sequence[tuple[str, Evaluation]]
) -> BenchmarkRun:
    """The run of ``row`` (its table's), from its evaluations (task, evaluation), in the
    benchmark's order of tasks."""
    per_task: list[list[float]] = []
    tasks: list[TaskScore] = []
    for name, evaluation in evaluations:
        task = benchmark.task(name)
        assert task is not None, f"{name} is not a task of {benchmark.name}"
        scores = scores_of(task, evaluation)
        per_task.append(scores)
        alone = aggregate([scores], seed=evaluation.id) if scores else None
        tasks.append(
            TaskScore(
                task=name,
                suite=evaluation.suite,
                evaluation=evaluation.id,
                status=evaluation.status,
                episodes=evaluation.episodes,
                done=len(scores),
                normalized_mean=alone.mean if alone else None,
                normalized_interval=alone.mean_interval if alone else None,
                verified=evaluation.verified,
            )
        )
    status = _status([e for _, e in evaluations])
    whole = aggregate(per_task, seed=row.id) if all(per_task) else None
    finished = row.finished
    ended = [e.finished for _, e in evaluations if e.finished is not None]
    return BenchmarkRun(
        id=row.id,
        benchmark=row.benchmark,
        suite=row.suite,
        repository=row.repository,
        ref=row.ref,
        commit=row.commit,
        submitter=row.submitter,
        status=status,
        created=dt.datetime.fromtimestamp(row.created, dt.UTC),
        finished=(
            dt.datetime.fromtimestamp(finished, dt.UTC)
            if finished is not None
            else (max(ended) if status.ended and ended else None)
        ),
        evaluations=tasks,
        episodes=sum(t.episodes for t in tasks),
        done=sum(t.done for t in tasks),
        **_aggregate(whole),
        profile=profile(per_task) if all(per_task) else [],
        verified=bool(tasks) and all(t.verified for t in tasks),
        signature=row.signature,
    )


def _aggregate(found: Aggregate | None) -> dict[str, Any]:
    if found is None:
        return {}
    return {
        "iqm": found.iqm,
        "iqm_interval": found.iqm_interval,
        "mean": found.mean,
        "mean_interval": found.mean_interval,
        "median": found.median,
        "median_interval": found.median_interval,
    }


def _status(evaluations: Sequence[Evaluation]) -> Status:
    if evaluations and all(e.status is Status.QUEUED for e in evaluations):
        return Status.QUEUED
    if any(not e.status.ended for e in evaluations):
        return Status.RUNNING
    if any(e.status is Status.CANCELLED for e in evaluations):
        return Status.CANCELLED
    return Status.FINISHED


def compare(
    a: BenchmarkRun,
    b: BenchmarkRun,
    benchmark: Benchmark,
    a_evaluations: Sequence[Evaluation],
    b_evaluations: Sequence[Evaluation],
) -> Compared:
    """The probability that A improves on B, over the tasks both ran (ValueError unless
    both are runs of one benchmark and suite and have ended)."""
    if (a.benchmark, a.suite) != (b.benchmark, b.suite):
        raise ValueError(
            f"run {a.id} is of {a.benchmark} ({a.suite}) and run {b.id} of {b.benchmark}"
            f" ({b.suite}): only runs of one benchmark and suite compare"
        )
    for run in (a, b):
        if not run.status.ended:
            raise ValueError(f"run {run.id} is {run.status}: runs compare once they have ended")
    a_scores, b_scores = [], []
    for task, ea, eb in zip(benchmark.tasks, a_evaluations, b_evaluations, strict=True):
        a_scores.append(scores_of(task, ea))
        b_scores.append(scores_of(task, eb))
    found = probability_of_improvement(a_scores, b_scores, seed=a.id * 100_003 + b.id)
    return Compared(
        a=a.id,
        b=b.id,
        benchmark=a.benchmark,
        probability_of_improvement=found.probability,
        interval=found.interval,
        tasks=len(a_scores),
    )


def statement(run: BenchmarkRun, signatures: Sequence[str], finished: float) -> dict[str, Any]:
    """What the lab vouches for when a run's evaluations have all ended: the commit, the
    benchmark and suite, each task's evaluation and the value of its signature (so the
    statement covers the evaluations'), and the aggregates."""
    return {
        "schema": BENCHMARK_RUN,
        "run": run.id,
        "benchmark": run.benchmark,
        "suite": run.suite,
        "repository": run.repository,
        "commit": run.commit,
        "status": run.status.value,
        "evaluations": [
            {"task": t.task, "evaluation": t.evaluation, "signature": s}
            for t, s in zip(run.evaluations, signatures, strict=True)
        ],
        "iqm": run.iqm,
        "iqm_interval": run.iqm_interval,
        "mean": run.mean,
        "median": run.median,
        "finished": dt.datetime.fromtimestamp(finished, dt.UTC).isoformat(),
    }


class BenchmarkLeaderRow(BaseModel):
    """A commit's row on a benchmark's leaderboard: its first run (``leaderboard``)."""

    model_config = ConfigDict(frozen=True)

    rank: int | None = Field(description="None: listed, not ranked (see note)")
    run: int
    repository: str
    commit: str
    iqm: float | None
    iqm_interval: tuple[float, float] | None
    mean: float | None
    episodes: int = Field(description="the run's episodes, every task's")
    status: Status
    verified: bool = Field(description="the lab's own replay verified every episode")
    tie: bool = Field(default=False, description="its IQM interval overlaps the ranked row above's")
    note: str | None = Field(default=None, description="why it is unranked")


def leaderboard(runs: Sequence[BenchmarkRun]) -> list[BenchmarkLeaderRow]:
    """Each commit's row: its first run (by submission) of ``runs`` (of one benchmark
    and suite), never its best. Runs that finished and verified are ranked by IQM,
    highest first; the rest follow, unranked, with why: still running, cancelled (a
    commit whose first run its submitter cancelled keeps that run as its row, so
    cancelling and resubmitting buys nothing), or not verified yet."""
    first: dict[str, BenchmarkRun] = {}
    for run in sorted(runs, key=lambda r: r.id):
        first.setdefault(run.commit, run)
    chosen = list(first.values())
    ranked = sorted((r for r in chosen if _unranked(r) is None), key=_rank_key)
    apart = sorted((r for r in chosen if _unranked(r) is not None), key=_rank_key)
    rows: list[BenchmarkLeaderRow] = []
    for run in ranked:
        above = rows[-1] if rows else None
        tie = (
            above is not None
            and above.iqm_interval is not None
            and run.iqm_interval is not None
            and Interval(*above.iqm_interval).overlaps(Interval(*run.iqm_interval))
        )
        rows.append(_leader_row(run, len(rows) + 1, tie, None))
    rows.extend(_leader_row(r, None, False, "not ranked: " + str(_unranked(r))) for r in apart)
    return rows


def _unranked(run: BenchmarkRun) -> str | None:
    """Why a commit's first run is not ranked (None: it is)."""
    if run.status is Status.CANCELLED:
        return "cancelled; it stays the commit's row (a later run does not replace it)"
    if not run.status.ended:
        return f"still {run.status.value}; ranked once every episode has ended and verified"
    if not run.verified or run.iqm is None:
        return "its episodes' replays are not all verified yet (the lab replays every record)"
    return None


def _rank_key(run: BenchmarkRun) -> tuple[float, int]:
    return (-(run.iqm if run.iqm is not None else float("-inf")), run.id)


def _leader_row(
    run: BenchmarkRun, rank: int | None, tie: bool, note: str | None
) -> BenchmarkLeaderRow:
    return BenchmarkLeaderRow(
        rank=rank,
        run=run.id,
        repository=run.repository,
        commit=run.commit,
        iqm=run.iqm,
        iqm_interval=run.iqm_interval,
        mean=run.mean,
        episodes=run.episodes,
        status=run.status,
        verified=run.verified,
        tie=tie,
        note=note,
    )
