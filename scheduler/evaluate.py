"""Evaluations: one commit queued on every episode of a task's suite, then signed.

Submitting an evaluation checks and resolves its repository once, as a trial's
submission does (``Submissions.prepare``), then queues one trial per episode of the
suite, all or none, in the transaction that writes the evaluation
(``Queue.submit_many``): each episode counts towards the submitter's daily limit, and
the queue's fair share runs them beside everyone else's trials, never all first. A
held-out suite's seeds come from the lab's secret here and go nowhere else but the
queue and the operator.

When an episode ends, its evaluation is looked at (``settle``): once the last has ended
the lab signs the evaluation's statement (``repository.evaluation.statement``).
Cancelling an evaluation cancels its episodes still queued and stops those running; the
ones that finished are kept, and its score is marked partial (an episode is never
cancelled alone). A rerun reruns every episode (the same commit, seeds and pinned data)
as a new evaluation under the rerunner's name, whose verdict says how many episodes
reproduced bit for bit.

A held-out suite is scored, not probed: each user has a budget of evaluations of it
(``HeldOutBudget``: so many per commit and suite version, so many a day), rerunning
included, checked in the transaction that queues them.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

from sqlalchemy.engine import Connection

from repository.evaluation import Evaluation, EvaluationRequest, Suite, statement
from repository.evaluation_index import Evaluations
from repository.index import User
from repository.signing import Keyring
from scheduler.errors import InvalidRequest, NotYours, OverBudget
from scheduler.queue import DAY, Queue
from scheduler.submit import Submissions

log = logging.getLogger("scheduler.evaluate")


@dataclass(frozen=True)
class HeldOutBudget:
    """How many evaluations of held-out suites a user may have: ``per_commit`` of one
    commit on one suite version (those the lab broke not counted), ``per_day`` in all
    over the last 24 hours. The leaderboard counts a commit's first evaluation anyway;
    the budget bounds what anyone can learn of the hidden episodes from aggregates."""

    per_commit: int = 1
    per_day: int = 5

    def check(
        self,
        evaluations: Evaluations,
        db: Connection,
        user: User,
        *,
        commit: str,
        task: str,
        suite: tuple[str, int],
        now: float,
    ) -> None:
        """``OverBudget`` if one more would take ``user`` past either limit."""
        of_commit, lately = evaluations.held_out_used(
            db, user.name, commit=commit, task=task, suite=suite, since=now - DAY
        )
        if of_commit >= self.per_commit:
            raise OverBudget(
                f"commit {commit[:12]} of {user.name}",
                of_commit,
                self.per_commit,
                f"on {task} suite {suite[0]} version {suite[1]}",
            )
        if lately >= self.per_day:
            raise OverBudget(user.name, lately, self.per_day, "in the last 24 hours")


class Evaluator:
    """Submits, cancels, reruns and signs evaluations."""

    def __init__(
        self,
        submissions: Submissions,
        evaluations: Evaluations,
        secret: bytes,
        keyring: Keyring | None,
        budget: HeldOutBudget | None = None,
    ) -> None:
        self.budget = budget or HeldOutBudget()
        self.submissions = submissions
        self.queue: Queue = submissions.queue
        self.host = submissions.host
        self.evaluations = evaluations
        self.secret = secret
        self.keyring = keyring
        self.queue.on_ended.append(self.settle)

    def suite(self, task: str, name: str) -> Suite:
        """Suite ``name`` of ``task``, as this lab runs it now (InvalidRequest if there is
        none, or if it is a held-out suite whose version was retired)."""
        suites = self.host.suites(task)
        found = next((s for s in suites if s.name == name), None)
        if found is None:
            known = ", ".join(s.name for s in suites) or "none"
            raise InvalidRequest(f"task {task} has no suite {name!r}; its suites: {known}")
        if found.held_out and (found.name, found.version) in self.evaluations.retired(task):
            raise InvalidRequest(
                f"suite {name} version {found.version} of {task} was retired: its seeds are"
                " public now, so it no longer holds anything out; the task needs a new"
                " version of it"
            )
        return found

    def submit(self, user: User, request: EvaluationRequest) -> int:
        """Check, resolve and queue every episode; the new evaluation's id.

        Raises InvalidRequest, RepositoryError or QuotaExceeded, having written nothing.
        """
        if request.task is not None:  # an unknown suite is refused before fetching
            self.suite(request.task, request.suite)
        prepared = self.submissions.prepare(request.repository, request.ref, request.task, {})
        asked = prepared.order
        assert asked.task is not None  # a prepared order names its task
        task = asked.task
        suite = self.suite(task, request.suite)
        values = self.host.check(task, suite.params)
        order = asked.model_copy(
            update={"params": {name: values[name] for name in sorted(suite.params)}}
        )
        seeds = suite.seeds_with(self.secret, task)
        task_version = self.host.task_version(task)

        def add(db: Connection, ids: list[int]) -> int:
            if suite.held_out:
                self._spend(db, user, order.commit, task, (suite.name, suite.version))
            return self.evaluations.add(
                db,
                order,
                task_version=task_version,
                suite=suite.name,
                suite_version=suite.version,
                held_out=suite.held_out,
                submitter=user.name,
                seeds=seeds,
                trial_ids=ids,
            )

        evaluation_id = self.queue.submit_many(
            user, [order.episode(seed) for seed in seeds], then=add
        )
        log.info(
            "evaluation %d queued for %s: %s, suite %s version %d, %d episodes",
            evaluation_id,
            user.name,
            prepared,
            suite.name,
            suite.version,
            len(seeds),
        )
        return evaluation_id

    def _spend(
        self, db: Connection, user: User, commit: str, task: str, suite: tuple[str, int]
    ) -> None:
        """Take one held-out evaluation of ``commit`` on ``task``'s suite (name, version)
        from ``user``'s budget (``OverBudget``), in the transaction that queues it."""
        self.budget.check(
            self.evaluations,
            db,
            user,
            commit=commit,
            task=task,
            suite=suite,
            now=self.queue.clock(),
        )

    def cancel(self, user: User, evaluation_id: int) -> Evaluation:
        """Cancel the episodes still queued and stop those running (``NotYours`` unless
        ``user`` submitted it); the evaluation after."""
        evaluation = self.evaluations.get(evaluation_id)
        if evaluation.submitter != user.name:
            raise NotYours(evaluation_id, evaluation.submitter, "cancel", what="evaluation")
        self.evaluations.request_cancel(evaluation_id)
        for trial_id in self.evaluations.trials(evaluation_id):
            self.queue.cancel(trial_id, user, whole=True)
        self.settle_evaluation(evaluation_id)  # if nothing was left to end
        return self.evaluations.get(evaluation_id)

    def rerun(self, user: User, evaluation_id: int) -> int:
        """Rerun every episode of an evaluation (of its original, for a rerun's rerun) as
        a new evaluation of ``user``'s (a held-out one within their budget); its id. The
        original's row on the leaderboard stays its submitter's."""
        old = self.evaluations.get(evaluation_id, reveal=True)
        if old.rerun_of is not None:
            old = self.evaluations.get(old.rerun_of, reveal=True)
        first = self.queue.index.trial(old.rows[0].trial)
        asked = first.order  # the evaluation's code, task and parameters, as its episodes'
        seeds = [r.seed for r in old.rows if r.seed is not None]  # revealed: every one
        assert len(seeds) == len(old.rows)
        hidden = old.held_out and (old.suite, old.suite_version) not in self.evaluations.retired(
            old.task
        )

        def add(db: Connection, ids: list[int]) -> int:
            if hidden:
                self._spend(db, user, old.commit, old.task, (old.suite, old.suite_version))
            return self.evaluations.add(
                db,
                asked.rerun(first.id),  # its code pinned at its commit, as each episode's
                task_version=old.task_version,
                suite=old.suite,
                suite_version=old.suite_version,
                held_out=old.held_out,
                submitter=user.name,
                seeds=seeds,
                trial_ids=ids,
                rerun_of=old.id,
            )

        # each episode's own rerun, of the very records its episodes learnt from
        orders = [
            asked.episode(row.seed).rerun(row.trial) for row in old.rows if row.seed is not None
        ]
        new_id = self.queue.submit_many(user, orders, then=add)
        log.info("evaluation %d queued for %s: a rerun of %d", new_id, user.name, old.id)
        return new_id

    def settle(self, trial_id: int) -> None:
        """After a trial ended: sign its evaluation if that was the last episode."""
        evaluation_id = self.evaluations.of_trial(trial_id)
        if evaluation_id is not None:
            self.settle_evaluation(evaluation_id)

    def settle_evaluation(self, evaluation_id: int) -> None:
        evaluation = self.evaluations.get(evaluation_id, reveal=True)  # signed whole
        if not evaluation.status.ended or evaluation.signature is not None:
            return
        finished = self.queue.clock()
        signature = None
        if self.keyring is not None:
            signature = self.keyring.sign(statement(evaluation, finished)).to_json()
        if self.evaluations.sign(evaluation_id, signature or {}, finished):
            score = evaluation.score
            log.info(
                "evaluation %d %s: %d of %d episodes succeeded",
                evaluation_id,
                evaluation.status,
                score.successes,
                score.episodes,
            )
