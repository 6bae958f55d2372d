"""Benchmark runs: one commit queued on every task of a benchmark, then signed.

Submitting a run checks and resolves the repository once, as an evaluation does
(``Submissions.prepare``), refuses it before anything is queued if ``lab.toml`` lists
the tasks it supports (``tasks = [...]``) and the benchmark has one outside the list,
then queues one evaluation per task, all or none, in one transaction: every episode of
every task counts towards the submitter's daily limit, and the queue's fair share runs
them beside everyone else's trials. The controller learns each episode's task from
``LAB_TASK``, whatever ``lab.toml``'s ``task`` says.

Each evaluation is signed as any other when its last episode ends
(``scheduler.evaluate.Evaluator``); when the run's last evaluation has ended, the lab
signs the run (``repository.benchmark_run.statement``), over the evaluations'
signatures. A run is of a public suite: the held-out suites' budgets are per
evaluation, and a benchmark would spend a day's in one go.
"""

from __future__ import annotations

import logging

from pydantic import BaseModel, ConfigDict, Field
from sqlalchemy.engine import Connection

from repository.benchmark import NAME
from repository.benchmark_index import BenchmarkRuns
from repository.benchmark_run import BenchmarkRun, statement
from repository.digests import canonical_json
from repository.index import User
from repository.signing import Keyring
from scheduler.errors import InvalidRequest
from scheduler.evaluate import Evaluator

log = logging.getLogger("scheduler.benchmarks")


class BenchmarkRunRequest(BaseModel):
    """What to run: a repository at a ref on every task of a benchmark."""

    model_config = ConfigDict(extra="forbid")

    repository: str = Field(min_length=1, max_length=2048, description="a git URL or path")
    ref: str | None = Field(None, max_length=256, description="branch, tag or commit")
    benchmark: str = Field(min_length=1, max_length=64, pattern=NAME.pattern)
    suite: str | None = Field(
        None,
        min_length=1,
        max_length=32,
        description="every task's suite (default: the one the benchmark names for each)",
    )


class BenchmarkRunner:
    """Submits and signs benchmark runs."""

    def __init__(self, evaluator: Evaluator, runs: BenchmarkRuns, keyring: Keyring | None) -> None:
        self.evaluator = evaluator
        self.runs = runs
        self.keyring = keyring
        self.queue = evaluator.queue
        self.host = evaluator.host
        # after the evaluator's own: a run is signed over its evaluations' signatures
        self.queue.on_ended.append(self.settle)

    def submit(self, user: User, request: BenchmarkRunRequest) -> int:
        """Check, resolve and queue every task's evaluation; the new run's id.

        Raises InvalidRequest, RepositoryError or QuotaExceeded, having written nothing.
        """
        benchmark = self.host.benchmark(request.benchmark)
        suites = []
        for task in benchmark.tasks:  # every suite checked before fetching anything
            suite = self.evaluator.suite(task.task, request.suite or task.suite)
            if suite.held_out:
                raise InvalidRequest(
                    f"suite {suite.name} of {task.task} is held out: a benchmark run is of"
                    " public suites (held-out suites are evaluated a task at a time, within"
                    " their budget)"
                )
            suites.append(suite)
        first = benchmark.tasks[0].task
        prepared = self.evaluator.submissions.prepare(request.repository, request.ref, first, {})
        if prepared.tasks:
            outside = [t.task for t in benchmark.tasks if t.task not in prepared.tasks]
            if outside:
                raise InvalidRequest(
                    f"lab.toml lists the tasks it supports ({', '.join(prepared.tasks)}), and"
                    f" {benchmark.name} has {len(outside)} outside them: {', '.join(outside)}"
                )
        asked = prepared.order
        plans = []
        for task, suite in zip(benchmark.tasks, suites, strict=True):
            values = self.host.check(task.task, suite.params)
            order = asked.model_copy(
                update={
                    "task": task.task,
                    "params": {name: values[name] for name in sorted(suite.params)},
                }
            )
            seeds = suite.seeds_with(self.evaluator.secret, task.task)
            plans.append((task.task, suite, order, seeds, self.host.task_version(task.task)))

        def add(db: Connection, ids: list[int]) -> int:
            made, start = [], 0
            for task, suite, order, seeds, version in plans:
                episodes = ids[start : start + len(seeds)]
                start += len(seeds)
                evaluation = self.evaluator.evaluations.add(
                    db,
                    order,
                    task_version=version,
                    suite=suite.name,
                    suite_version=suite.version,
                    held_out=False,
                    submitter=user.name,
                    seeds=seeds,
                    trial_ids=episodes,
                )
                made.append((task, evaluation))
            return self.runs.add(
                db,
                asked,
                benchmark=benchmark.name,
                suite=request.suite or "",
                submitter=user.name,
                evaluations=made,
            )

        orders = [order.episode(seed) for _, _, order, seeds, _ in plans for seed in seeds]
        run_id = self.queue.submit_many(user, orders, then=add)
        log.info(
            "benchmark run %d queued for %s: %s on %s, %d tasks, %d episodes",
            run_id,
            user.name,
            prepared,
            benchmark.name,
            len(plans),
            len(orders),
        )
        return run_id

    def settle(self, trial_id: int) -> None:
        """After a trial ended: sign its benchmark run if that was the last episode."""
        evaluation_id = self.evaluator.evaluations.of_trial(trial_id)
        if evaluation_id is None:
            return
        run_id = self.runs.of_evaluation(evaluation_id)
        if run_id is not None:
            self.settle_run(run_id)

    def settle_run(self, run_id: int) -> BenchmarkRun:
        run = self.runs.get(run_id)
        if not run.status.ended or run.signature is not None:
            return run
        _, evaluations = self.runs.whole(run_id)
        finished = self.queue.clock()
        signed = [canonical_json(e.signature) if e.signature else "" for _, e in evaluations]
        signature = None
        if self.keyring is not None:
            signature = self.keyring.sign(statement(run, signed, finished)).to_json()
        if self.runs.sign(run_id, signature or {}, finished):
            log.info(
                "benchmark run %d %s: IQM %s over %d episodes",
                run_id,
                run.status,
                run.iqm,
                run.done,
            )
        return self.runs.get(run_id)
