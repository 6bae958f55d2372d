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
ones that finished are kept, and its score is marked partial. A rerun reruns every
episode (the same commit, seeds and pinned data) as a new evaluation, whose verdict says
how many episodes reproduced bit for bit.
"""

from __future__ import annotations

import logging

from repository.evaluation import Evaluation, EvaluationRequest, Suite, statement
from repository.evaluation_index import Evaluations
from repository.index import User
from repository.signing import Keyring
from scheduler.errors import InvalidRequest, NotYours
from scheduler.queue import Queue
from scheduler.submit import Submissions

log = logging.getLogger("scheduler.evaluate")


class Evaluator:
    """Submits, cancels, reruns and signs evaluations."""

    def __init__(
        self,
        submissions: Submissions,
        evaluations: Evaluations,
        secret: bytes,
        keyring: Keyring | None,
    ) -> None:
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
        suite = self.suite(prepared.task, request.suite)
        values = self.host.check(prepared.task, suite.params)
        params = {name: values[name] for name in sorted(suite.params)}
        seeds = suite.seeds_with(self.secret, prepared.task)
        task_version = self.host.task_version(prepared.task)
        resolved = prepared.resolved
        evaluation_id = self.queue.submit_many(
            user,
            seeds,
            lambda db, ids: self.evaluations.add(
                db,
                task=prepared.task,
                task_version=task_version,
                suite=suite.name,
                suite_version=suite.version,
                held_out=suite.held_out,
                repository=resolved.repository,
                ref=request.ref,
                commit=resolved.commit,
                params=params,
                submitter=user.name,
                seeds=seeds,
                trial_ids=ids,
            ),
            repository=resolved.repository,
            ref=request.ref,
            commit=resolved.commit,
            task=prepared.task,
            params=params,
            public=resolved.public,
            data=prepared.data,
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

    def cancel(self, user: User, evaluation_id: int) -> Evaluation:
        """Cancel the episodes still queued and stop those running (``NotYours`` unless
        ``user`` submitted it); the evaluation after."""
        evaluation = self.evaluations.get(evaluation_id)
        if evaluation.submitter != user.name:
            raise NotYours(evaluation_id, evaluation.submitter, "cancel", what="evaluation")
        self.evaluations.request_cancel(evaluation_id)
        for trial_id in self.evaluations.trials(evaluation_id):
            self.queue.cancel(trial_id, user)
        self.settle_evaluation(evaluation_id)  # if nothing was left to end
        return self.evaluations.get(evaluation_id)

    def rerun(self, user: User, evaluation_id: int) -> int:
        """Rerun every episode of an evaluation (of its original, for a rerun's rerun) as
        a new evaluation; its id."""
        old = self.evaluations.get(evaluation_id, reveal=True)
        if old.rerun_of is not None:
            old = self.evaluations.get(old.rerun_of, reveal=True)
        first = self.queue.index.trial(old.rows[0].trial)
        seeds = [r.seed for r in old.rows if r.seed is not None]  # revealed: every one
        assert len(seeds) == len(old.rows)
        new_id = self.queue.submit_many(
            user,
            seeds,
            lambda db, ids: self.evaluations.add(
                db,
                task=old.task,
                task_version=old.task_version,
                suite=old.suite,
                suite_version=old.suite_version,
                held_out=old.held_out,
                repository=old.repository,
                ref=old.commit,
                commit=old.commit,
                params=old.params,
                submitter=user.name,
                seeds=seeds,
                trial_ids=ids,
                rerun_of=old.id,
            ),
            repository=old.repository,
            ref=old.commit,
            commit=old.commit,
            task=old.task,
            params=old.params,
            public=first.public,
            rerun_of=[r.trial for r in old.rows],
            data=first.data,  # the very records its episodes learnt from
        )
        log.info("evaluation %d queued for %s: a rerun of %d", new_id, user.name, old.id)
        return new_id

    def settle(self, trial_id: int) -> None:
        """After a trial ended: sign its evaluation if that was the last episode."""
        evaluation_id = self.evaluations.of_trial(trial_id)
        if evaluation_id is not None:
            self.settle_evaluation(evaluation_id)

    def settle_evaluation(self, evaluation_id: int) -> None:
        evaluation = self.evaluations.get(evaluation_id)
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
