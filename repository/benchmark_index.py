"""The benchmark runs in the index: their rows and the evaluation of each task.

A run's row says what was run (benchmark, suite, repository and commit); its
``benchmark_run_evaluations`` tie each task of the benchmark to its evaluation. What a
run adds up to is read from those evaluations whenever it is asked for
(``repository.benchmark_run``); once the last has ended the lab signs it once.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import Any

import sqlalchemy as sa
from sqlalchemy.engine import Connection

from repository.benchmark import Benchmark
from repository.benchmark_run import BenchmarkRun, run_of
from repository.errors import RecordNotFound
from repository.evaluation import Evaluation
from repository.evaluation_index import Evaluations
from repository.index import Index
from repository.tables import benchmark_run_evaluations, benchmark_runs
from repository.trial import Order

R = benchmark_runs.c
L = benchmark_run_evaluations.c
Benchmarks = Callable[[str], Benchmark]  # a benchmark's name -> its declaration


class BenchmarkRuns:
    """The benchmark runs on ``index``, their evaluations read from ``evaluations``."""

    def __init__(self, index: Index, evaluations: Evaluations, benchmarks: Benchmarks) -> None:
        self.index = index
        self.evaluations = evaluations
        self.benchmarks = benchmarks

    def add(
        self,
        db: Connection,
        order: Order,
        *,
        benchmark: str,
        suite: str,
        submitter: str,
        evaluations: Sequence[tuple[str, int]],
    ) -> int:
        """Insert a run of ``order``'s code on ``benchmark`` whose evaluations (task,
        evaluation id, in the benchmark's order) were just added in ``db``; its id."""
        result = db.execute(
            sa.insert(benchmark_runs).values(
                benchmark=benchmark,
                suite=suite,
                repository=order.repository,
                ref=order.ref,
                commit=order.commit,
                submitter=submitter,
                created=self.index.clock(),
            )
        )
        key = result.inserted_primary_key
        assert key is not None
        run_id = int(key[0])
        db.execute(
            sa.insert(benchmark_run_evaluations),
            [
                {"run_id": run_id, "place": n, "task": task, "evaluation_id": evaluation}
                for n, (task, evaluation) in enumerate(evaluations)
            ],
        )
        return run_id

    def get(self, run_id: int) -> BenchmarkRun:
        """One run (RecordNotFound)."""
        row, found = self.whole(run_id)
        return run_of(row, self.benchmarks(row.benchmark), found)

    def whole(self, run_id: int) -> tuple[Any, list[tuple[str, Evaluation]]]:
        """A run's row and its evaluations (task, evaluation), in the benchmark's order."""
        with self.index.engine.connect() as db:
            row = db.execute(sa.select(benchmark_runs).where(R.id == run_id)).one_or_none()
            if row is None:
                raise RecordNotFound("benchmark run", str(run_id))
            links = db.execute(
                sa.select(L.task, L.evaluation_id).where(L.run_id == run_id).order_by(L.place)
            ).all()
        return row, [(task, self.evaluations.get(evaluation)) for task, evaluation in links]

    def find(
        self,
        *,
        benchmark: str | None = None,
        commit: str | None = None,
        limit: int = 50,
        before: int | None = None,
    ) -> tuple[list[BenchmarkRun], int | None]:
        """Runs, newest first, a page at a time: the page and the ``before`` of the next."""
        query = sa.select(R.id)
        if benchmark is not None:
            query = query.where(R.benchmark == benchmark)
        if commit is not None:
            query = query.where(R.commit == commit.lower())
        if before is not None:
            query = query.where(R.id < before)
        with self.index.engine.connect() as db:
            ids = list(db.execute(query.order_by(R.id.desc()).limit(limit + 1)).scalars())
        more = len(ids) > limit
        runs = [self.get(i) for i in ids[:limit]]
        return runs, (runs[-1].id if more and runs else None)

    def of_evaluation(self, evaluation_id: int) -> int | None:
        """The run the evaluation is a task of, if any."""
        with self.index.engine.connect() as db:
            return db.execute(sa.select(L.run_id).where(L.evaluation_id == evaluation_id)).scalar()

    def sign(self, run_id: int, signature: Mapping[str, Any], finished: float) -> bool:
        """Keep the lab's signature of a run whose evaluations have all ended; False if it
        was signed already (the first signature stays)."""
        with self.index.begin() as db:
            return (
                db.execute(
                    sa.update(benchmark_runs)
                    .where(R.id == run_id, R.signature.is_(None))
                    .values(signature=dict(signature), finished=finished)
                ).rowcount
                == 1
            )
