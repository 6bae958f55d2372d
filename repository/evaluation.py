"""The evaluation record, typed: a commit scored on a task's fixed suite of episodes.

A task declares named **suites** (``Suite``): a public ``dev`` suite lists its seeds; a
held-out suite (``test``) gives only how many episodes it has, and its seeds derive from
a secret of the lab (``held_out_seeds``), so nobody can tune a controller to them. A
suite has a version, bumped whenever its episodes change; two evaluations compare only
on the same task version and suite version.

An **evaluation** is one commit run on every episode of one suite: its episodes are
ordinary trials (pinned, sandboxed, filed, replayed and signed as any), and the
evaluation says what they add up to (``Evaluation``): how many succeeded, the success
rate with its 95 % Wilson interval, the mean reward with its bootstrap interval
(``repository.stats``), whether every episode's replay verified, and the lab's signature
over the statement of its episodes. Its status follows its episodes: ``queued`` until
one starts, ``running``, then ``finished`` when all have, or ``cancelled`` (whatever
finished before is kept, and the score is marked ``partial``).

A held-out suite's seeds and records are the operator's alone until the operator retires
that suite version; the submitter sees each episode's outcome and reward.
"""

from __future__ import annotations

import datetime as dt
import hashlib
import hmac
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from pydantic import BaseModel, ConfigDict, Field

from repository.stats import Interval, bootstrap_mean, mcnemar_exact, paired_difference, wilson
from repository.trial import MAX_SEED, Outcome, Status, Value

EVALUATION = "labd.evaluation/1"  # what an evaluation's signed statement says it is
SUITE_NAME = re.compile(r"[a-z][a-z0-9-]{0,31}", re.ASCII)
MAX_EPISODES = 1000


@dataclass(frozen=True)
class Suite:
    """A named, versioned set of episodes of a task, as the task declares it.

    A public suite lists its ``seeds``; a held-out one (``held_out``) has ``episodes``
    seeds that the lab derives from its secret. Every episode runs with ``params``
    (the task's defaults for what it does not name).
    """

    name: str
    version: int
    seeds: tuple[int, ...] = ()
    episodes: int = 0  # held-out suites: how many; public ones: len(seeds)
    held_out: bool = False
    params: Mapping[str, Value] = field(default_factory=dict)
    doc: str = ""

    def __post_init__(self) -> None:
        if not SUITE_NAME.fullmatch(self.name):
            raise ValueError(f"suite name {self.name!r}: lower-case letters, digits, '-'")
        if self.version < 1:
            raise ValueError(f"suite {self.name}: versions start at 1")
        if self.held_out:
            if self.seeds:
                raise ValueError(f"suite {self.name} is held out: its seeds are the lab's secret")
        else:
            if self.episodes not in (0, len(self.seeds)):
                raise ValueError(
                    f"suite {self.name}: {self.episodes} episodes, {len(self.seeds)} seeds"
                )
            object.__setattr__(self, "episodes", len(self.seeds))
            if len(set(self.seeds)) != len(self.seeds):
                raise ValueError(f"suite {self.name} lists a seed twice")
            if any(not 0 <= s <= MAX_SEED for s in self.seeds):
                raise ValueError(f"suite {self.name}: seeds from 0 to {MAX_SEED}")
        if not 1 <= self.episodes <= MAX_EPISODES:
            raise ValueError(f"suite {self.name}: from 1 to {MAX_EPISODES} episodes")

    def seeds_with(self, secret: bytes, task: str) -> list[int]:
        """Every episode's seed, in order (a held-out suite's from ``secret``)."""
        if not self.held_out:
            return list(self.seeds)
        return held_out_seeds(secret, task, self.name, self.version, self.episodes)


def held_out_seeds(secret: bytes, task: str, suite: str, version: int, episodes: int) -> list[int]:
    """A held-out suite version's seeds: HMAC-SHA256 of the lab's secret over the task,
    suite, version and episode, as 63-bit numbers; the same on every run of this lab,
    unguessable without its secret, and different for each suite version."""
    seeds = []
    for episode in range(episodes):
        message = f"labd suite {task} {suite} {version} {episode}".encode()
        digest = hmac.new(secret, message, hashlib.sha256).digest()
        seeds.append(int.from_bytes(digest[:8], "big") & MAX_SEED)
    return seeds


class SuiteInfo(BaseModel):
    """A suite as ``GET /api/tasks/{name}`` lists it (a held-out suite without seeds)."""

    model_config = ConfigDict(frozen=True)

    name: str
    version: int
    episodes: int
    held_out: bool
    retired: bool = Field(default=False, description="held-out suites: retired, so public now")
    seeds: list[int] | None = Field(default=None, description="public suites only")
    params: dict[str, Value] = Field(default_factory=dict)
    doc: str = ""


class EvaluationRequest(BaseModel):
    """What to evaluate: a repository at a ref on one suite of a task."""

    model_config = ConfigDict(extra="forbid")

    repository: str = Field(min_length=1, max_length=2048, description="a git URL or path")
    ref: str | None = Field(None, max_length=256, description="branch, tag or commit")
    task: str | None = Field(
        None, min_length=1, max_length=64, description="by default the one lab.toml names"
    )
    suite: str = Field("dev", min_length=1, max_length=32, description="a suite of the task")


class EpisodeRow(BaseModel):
    """One episode of an evaluation: its trial and how it went.

    ``seed`` is None where the caller may not see it (a held-out suite not retired)."""

    model_config = ConfigDict(frozen=True)

    episode: int = Field(description="its place in the suite, from 0")
    trial: int
    seed: int | None
    status: Status
    outcome: Outcome | None
    reward: float | None
    data_digest: str | None = None
    verified: bool | None = Field(
        default=None, description="its replay verified; None: not (yet) replayed"
    )
    compute_seconds: float | None = None
    reproduced: bool | None = Field(
        default=None, description="reruns: an identical data digest to the original episode's"
    )


class Score(BaseModel):
    """What an evaluation's episodes add up to (finished episodes only)."""

    model_config = ConfigDict(frozen=True)

    episodes: int
    done: int = Field(description="episodes finished (any outcome)")
    running: int
    queued: int
    successes: int
    errors: int
    success_rate: float | None = Field(description="successes over finished episodes")
    success_interval: tuple[float, float] | None = Field(description="95 % Wilson interval")
    mean_reward: float | None
    reward_interval: tuple[float, float] | None = Field(
        description="95 % percentile bootstrap over episodes"
    )
    verified: bool = Field(description="every episode finished and its replay verified")
    compute_seconds: float


class Evaluation(Score):
    """An evaluation's whole record, as the API serves it: its score's fields (``Score``),
    then what was evaluated, where it is, and its episodes."""

    model_config = ConfigDict(frozen=True)

    id: int
    task: str
    task_version: str
    suite: str
    suite_version: int
    held_out: bool
    repository: str
    ref: str | None
    commit: str
    params: dict[str, Value]
    submitter: str
    rerun_of: int | None
    status: Status
    partial: bool = Field(description="cancelled before every episode finished")
    created: dt.datetime
    finished: dt.datetime | None
    rows: list[EpisodeRow]
    reproduced: str | None = Field(default=None, description="reruns: the verdict in words")
    signature: dict[str, Any] | None = None

    @property
    def score(self) -> Score:
        """Its score alone."""
        return Score(**{name: getattr(self, name) for name in Score.model_fields})


def score(rows: Sequence[EpisodeRow], *, seed: int) -> Score:
    """What ``rows`` add up to; the reward interval's resampling is seeded with ``seed``."""
    finished = [r for r in rows if r.status is Status.FINISHED]
    successes = sum(r.outcome is Outcome.SUCCESS for r in finished)
    rewards = [r.reward for r in finished if r.reward is not None]
    interval = wilson(successes, len(finished)) if finished else None
    spread = bootstrap_mean(rewards, seed=seed)
    return Score(
        episodes=len(rows),
        done=len(finished),
        running=sum(r.status is Status.RUNNING for r in rows),
        queued=sum(r.status is Status.QUEUED for r in rows),
        successes=successes,
        errors=sum(r.outcome is Outcome.ERROR for r in finished),
        success_rate=successes / len(finished) if finished else None,
        success_interval=_pair(interval),
        mean_reward=sum(rewards) / len(rewards) if rewards else None,
        reward_interval=_pair(spread),
        verified=bool(rows) and all(r.verified for r in rows),
        compute_seconds=round(sum(r.compute_seconds or 0.0 for r in rows), 3),
    )


def reproduced(rows: Sequence[EpisodeRow]) -> str:
    """A rerun evaluation's verdict in words: how many episodes reproduced their
    original's data, bit for bit, and which did not."""
    done = [r for r in rows if r.status.ended]
    if len(done) < len(rows):
        return f"pending: {len(done)} of {len(rows)} episodes rerun so far"
    diverged = [r.episode for r in rows if r.reproduced is not True]
    if not diverged:
        return f"reproduced: {len(rows)} of {len(rows)} episodes identical"
    listed = ", ".join(str(e) for e in diverged[:10]) + (", ..." if len(diverged) > 10 else "")
    return (
        f"diverged: {len(rows) - len(diverged)} of {len(rows)} episodes identical;"
        f" episodes {listed} differ"
    )


def status_of(rows: Sequence[EpisodeRow], cancel_requested: bool) -> Status:
    """An evaluation's status from its episodes'."""
    if rows and all(r.status is Status.QUEUED for r in rows) and not cancel_requested:
        return Status.QUEUED
    if any(not r.status.ended for r in rows):
        return Status.RUNNING
    if cancel_requested and any(r.status is Status.CANCELLED for r in rows):
        return Status.CANCELLED
    return Status.FINISHED


def statement(evaluation: Evaluation, finished: float) -> dict[str, Any]:
    """What the lab vouches for when every episode of an evaluation has ended: the
    commit, the suite and its version, and each episode's trial, data digest, outcome
    and reward (a held-out suite's seeds left out: the signature is public)."""
    return {
        "schema": EVALUATION,
        "evaluation": evaluation.id,
        "repository": evaluation.repository,
        "commit": evaluation.commit,
        "task": evaluation.task,
        "task_version": evaluation.task_version,
        "suite": evaluation.suite,
        "suite_version": evaluation.suite_version,
        "held_out": evaluation.held_out,
        "status": evaluation.status.value,
        "episodes": [
            {
                "episode": r.episode,
                "trial": r.trial,
                **({} if evaluation.held_out else {"seed": r.seed}),
                "status": r.status.value,
                "outcome": r.outcome.value if r.outcome else None,
                "reward": r.reward,
                "data_digest": r.data_digest,
            }
            for r in evaluation.rows
        ],
        "success_rate": evaluation.score.success_rate,
        "finished": dt.datetime.fromtimestamp(finished, dt.UTC).isoformat(),
    }


class Pairs(BaseModel):
    """Two evaluations' episodes paired: how many each way."""

    model_config = ConfigDict(frozen=True)

    both: int
    only_a: int
    only_b: int
    neither: int


class Comparison(BaseModel):
    """Two evaluations of one suite version, paired by episode."""

    model_config = ConfigDict(frozen=True)

    a: int
    b: int
    task: str
    suite: str
    suite_version: int
    paired: int = Field(description="episodes finished in both")
    pairs: Pairs
    p_value: float = Field(description="McNemar's exact test on the discordant pairs")
    reward_difference: float | None = Field(description="mean of A's reward minus B's")
    reward_difference_interval: tuple[float, float] | None
    said: str = Field(description="the comparison in one sentence")


def compare(a: Evaluation, b: Evaluation) -> Comparison:
    """Pair ``a`` and ``b`` by episode (ValueError if they are not of one suite version)."""
    if (a.task, a.suite) != (b.task, b.suite):
        raise ValueError(
            f"evaluation {a.id} is of {a.task} suite {a.suite}, {b.id} of {b.task} suite"
            f" {b.suite}: only evaluations of one suite compare"
        )
    if (a.task_version, a.suite_version) != (b.task_version, b.suite_version):
        raise ValueError(
            f"evaluation {a.id} ran {a.task} {a.task_version} suite {a.suite} version"
            f" {a.suite_version}, {b.id} ran {b.task_version} version {b.suite_version}:"
            " their episodes differ, so they do not pair"
        )
    theirs = {r.episode: r for r in b.rows if r.status is Status.FINISHED}
    paired = [
        (r, theirs[r.episode])
        for r in a.rows
        if r.status is Status.FINISHED and r.episode in theirs
    ]
    won = [(x.outcome is Outcome.SUCCESS, y.outcome is Outcome.SUCCESS) for x, y in paired]
    pairs = Pairs(
        both=sum(x and y for x, y in won),
        only_a=sum(x and not y for x, y in won),
        only_b=sum(y and not x for x, y in won),
        neither=sum(not (x or y) for x, y in won),
    )
    rewarded = [
        (x.reward, y.reward) for x, y in paired if x.reward is not None and y.reward is not None
    ]
    difference = paired_difference(
        [x for x, _ in rewarded], [y for _, y in rewarded], seed=a.id * 1_000_003 + b.id
    )
    p = mcnemar_exact(pairs.only_a, pairs.only_b)
    return Comparison(
        a=a.id,
        b=b.id,
        task=a.task,
        suite=a.suite,
        suite_version=a.suite_version,
        paired=len(paired),
        pairs=pairs,
        p_value=p,
        reward_difference=difference[0] if difference else None,
        reward_difference_interval=_pair(difference[1]) if difference else None,
        said=_said(a.id, b.id, pairs, len(paired), p),
    )


def _said(a: int, b: int, pairs: Pairs, paired: int, p: float) -> str:
    if paired == 0:
        return f"Evaluations {a} and {b} have no finished episode in common yet."
    if pairs.only_a == pairs.only_b == 0:
        return (
            f"A ({a}) and B ({b}) succeed on the same {pairs.both} of {paired} episodes:"
            " nothing tells them apart."
        )
    verdict = (
        "a difference this large is unlikely by chance"
        if p < 0.05
        else "a difference this small could be chance"
    )
    if pairs.only_b > pairs.only_a:  # the better one first
        return (
            f"B ({b}) succeeds on {_episodes(pairs.only_b)} where A ({a}) fails, A on"
            f" {pairs.only_a} where B fails: p = {p:.2g}; {verdict}."
        )
    return (
        f"A ({a}) succeeds on {_episodes(pairs.only_a)} where B ({b}) fails, B on"
        f" {pairs.only_b} where A fails: p = {p:.2g}; {verdict}."
    )


def _episodes(n: int) -> str:
    return f"{n} episode" if n == 1 else f"{n} episodes"


class LeaderRow(BaseModel):
    """A commit's best evaluation on a suite: a row of the task's leaderboard."""

    model_config = ConfigDict(frozen=True)

    rank: int
    evaluation: int
    repository: str
    commit: str
    submitter: str
    episodes: int
    success_rate: float
    success_interval: tuple[float, float]
    mean_reward: float | None
    reward_interval: tuple[float, float] | None
    verified: bool
    tie: bool = Field(description="its success interval overlaps the row above's")


def leaderboard(evaluations: Sequence[Evaluation]) -> list[LeaderRow]:
    """Finished, complete evaluations ranked by success rate then mean reward, each
    commit's best one only."""
    best: dict[str, Evaluation] = {}
    for e in evaluations:
        if e.status is not Status.FINISHED or e.partial or e.score.success_rate is None:
            continue
        if e.commit not in best or _rank_key(e) < _rank_key(best[e.commit]):
            best[e.commit] = e
    rows: list[LeaderRow] = []
    for e in sorted(best.values(), key=_rank_key):
        s = e.score
        assert s.success_rate is not None and s.success_interval is not None
        above = rows[-1] if rows else None
        rows.append(
            LeaderRow(
                rank=len(rows) + 1,
                evaluation=e.id,
                repository=e.repository,
                commit=e.commit,
                submitter=e.submitter,
                episodes=s.episodes,
                success_rate=s.success_rate,
                success_interval=s.success_interval,
                mean_reward=s.mean_reward,
                reward_interval=s.reward_interval,
                verified=s.verified,
                tie=above is not None
                and Interval(*above.success_interval).overlaps(Interval(*s.success_interval)),
            )
        )
    return rows


def _rank_key(e: Evaluation) -> tuple[float, float, int]:
    reward = e.score.mean_reward
    return (
        -(e.score.success_rate or 0.0),
        -(reward if reward is not None else float("-inf")),
        e.id,
    )


def _pair(interval: Interval | None) -> tuple[float, float] | None:
    return (interval.low, interval.high) if interval is not None else None
