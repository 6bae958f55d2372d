"""The evaluation record, typed: a commit scored on a task's fixed suite of episodes.

A task declares named **suites** (``Suite``): a public ``dev`` suite lists its seeds; a
held-out suite (``test``) gives only how many episodes it has, and its seeds derive from
a secret of the lab (``held_out_seeds``), so nobody can tune a controller to them. A
suite has a version, bumped whenever its episodes change; two evaluations compare only
on the same task version and suite version.

An **evaluation** is one commit run on every episode of one suite: its episodes are
ordinary trials (pinned, sandboxed, filed, replayed and signed as any), and the
evaluation says what they add up to (``Evaluation``): how many succeeded, the success
rate over the suite's episodes with its 95 % Wilson interval, the mean reward with its
bootstrap interval (``repository.stats``), whether every episode's replay verified, and
the lab's signature over the statement of its episodes. Its status follows its episodes:
``queued`` until one starts, ``running``, then ``finished`` when all have, or
``cancelled``. Every episode counts: one cancelled, or broken by the lab rather than by
the controller (``lab_fault``), makes the evaluation ``partial``, and a partial score is
never ranked.

A held-out suite's episodes are blind and private until the operator retires that suite
version: the controller is told no seed, and everyone but the operator sees the
evaluation's aggregate alone (``Evaluation.hidden``): no per-episode rows, timings,
records or logs, and no progress while it runs. Its signed statement commits to the
episodes by a digest (``episodes_sha256``) that anyone can check once they are public.

The leaderboard (``leaderboard``) ranks each commit by its first evaluation of the suite
version that the lab did not break, never by its best: reruns verify, they never replace
a row, and an evaluation its submitter cancelled stands as the commit's row, unranked.
"""

from __future__ import annotations

import datetime as dt
import hashlib
import hmac
import json
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from pydantic import BaseModel, ConfigDict, Field

from repository.stats import (
    MIN_BOOTSTRAP,
    Interval,
    mcnemar_exact,
    mean_interval,
    paired_difference,
    wilson,
)
from repository.trial import MAX_SEED, Outcome, Status, Value

EVALUATION = "labd.evaluation/2"  # what an evaluation's signed statement says it is
SUITE_NAME = re.compile(r"[a-z][a-z0-9-]{0,31}", re.ASCII)
MAX_EPISODES = 1000
# Why an evaluation is partial (``Evaluation.partial_cause``)
CANCELLED = "cancelled"  # it, or an episode of it, was cancelled
LAB_BROKE = "lab"  # the lab broke an episode (``lab_fault``): not the controller's error


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
    replayed_elsewhere: bool | None = Field(
        default=None,
        description="its replay ran on another node of the lab's cluster than the episode;"
        " None: not replayed by the cluster",
    )
    compute_seconds: float | None = None
    reproduced: bool | None = Field(
        default=None, description="reruns: an identical data digest to the original episode's"
    )
    lab_fault: bool = Field(default=False, description="an error of the lab's making")

    def stated(self) -> dict[str, Any]:
        """What a signed statement says of the episode (``statement``)."""
        return {
            "episode": self.episode,
            "trial": self.trial,
            "seed": self.seed,
            "status": self.status.value,
            "outcome": self.outcome.value if self.outcome else None,
            "reward": self.reward,
            "data_digest": self.data_digest,
        }


class Score(BaseModel):
    """What an evaluation's episodes add up to.

    The counts are None where the caller may not follow a held-out evaluation episode by
    episode (``Evaluation.hidden``, while it runs); the rate is over the suite's
    episodes, known once every episode has ended."""

    model_config = ConfigDict(frozen=True)

    episodes: int
    done: int | None = Field(description="episodes finished (any outcome)")
    running: int | None
    queued: int | None
    successes: int | None
    errors: int | None
    success_rate: float | None = Field(
        description="successes over the suite's episodes (a cancelled or unfinished one is no"
        " success), once every episode has ended"
    )
    success_interval: tuple[float, float] | None = Field(description="95 % Wilson interval")
    mean_reward: float | None
    reward_interval: tuple[float, float] | None = Field(
        description="95 % percentile bootstrap over episodes; null with fewer than"
        f" {MIN_BOOTSTRAP} rewards or all alike, where a bootstrap is no 95 % interval"
    )
    verified: bool = Field(description="every episode finished and the lab's replay verified it")
    verified_elsewhere: int | None = Field(
        default=None,
        description="episodes whose replay verified on another machine of the lab's cluster"
        " than the one that ran them; None: none was replayed by a cluster",
    )
    compute_seconds: float | None = Field(
        description="the episodes' wall time added up; None for a hidden evaluation"
    )


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
    partial: bool = Field(
        description="an episode was cancelled, or broken by the lab: not every episode counted,"
        " so the score is never ranked"
    )
    partial_cause: str | None = Field(
        default=None, description=f"'{CANCELLED}' or '{LAB_BROKE}' (the lab broke an episode)"
    )
    partial_reason: str | None = Field(default=None, description="why it is partial, in words")
    hidden: bool = Field(
        default=False,
        description="a held-out suite not yet retired: its episodes (rows, timings, records,"
        " logs) are the operator's; everyone else sees the aggregate once it has ended",
    )
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
    """What ``rows`` add up to; the reward interval's resampling is seeded with ``seed``.

    The success rate and its interval are over every episode of the suite, once every
    one has ended: a cancelled episode, or one the lab broke, is no success (such an
    evaluation is partial, and never ranked, but its rate never rises by an episode
    left out)."""
    finished = [r for r in rows if r.status is Status.FINISHED]
    successes = sum(r.outcome is Outcome.SUCCESS for r in finished)
    rewards = [r.reward for r in finished if r.reward is not None]
    ended = bool(rows) and all(r.status.ended for r in rows)
    interval = wilson(successes, len(rows)) if ended else None
    spread = mean_interval(rewards, seed=seed)  # None where it would be degenerate
    return Score(
        episodes=len(rows),
        done=len(finished),
        running=sum(r.status is Status.RUNNING for r in rows),
        queued=sum(r.status is Status.QUEUED for r in rows),
        successes=successes,
        errors=sum(r.outcome is Outcome.ERROR for r in finished),
        success_rate=successes / len(rows) if ended else None,
        success_interval=_pair(interval),
        mean_reward=sum(rewards) / len(rewards) if rewards else None,
        reward_interval=_pair(spread),
        verified=bool(rows) and all(r.verified for r in rows),
        verified_elsewhere=_elsewhere(rows),
        compute_seconds=round(sum(r.compute_seconds or 0.0 for r in rows), 3),
    )


def _elsewhere(rows: Sequence[EpisodeRow]) -> int | None:
    """Episodes verified on another machine than their own (None: no cluster replayed)."""
    if all(r.replayed_elsewhere is None for r in rows):
        return None
    return sum(bool(r.verified and r.replayed_elsewhere) for r in rows)


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
    """An evaluation's status from its episodes': ``cancelled`` once every episode has
    ended if any of them was cancelled (a cancel that came after every episode had
    ended cancelled nothing: the evaluation is finished, and whole)."""
    if rows and all(r.status is Status.QUEUED for r in rows) and not cancel_requested:
        return Status.QUEUED
    if any(not r.status.ended for r in rows):
        return Status.RUNNING
    if any(r.status is Status.CANCELLED for r in rows):
        return Status.CANCELLED
    return Status.FINISHED


def partiality(rows: Sequence[EpisodeRow], cancel_requested: bool) -> tuple[str, str] | None:
    """Why an ended evaluation did not count every episode: its cause (``CANCELLED`` or
    ``LAB_BROKE``) and the reason in words; None if it did, or has not ended."""
    if any(not r.status.ended for r in rows):
        return None
    cancelled = [r.episode for r in rows if r.status is Status.CANCELLED]
    if cancelled and cancel_requested:
        return CANCELLED, f"cancelled by its submitter ({_episodes(len(cancelled))} unfinished)"
    if cancelled:
        return CANCELLED, f"{_episodes(len(cancelled))} cancelled ({_listed(cancelled)})"
    broken = [r.episode for r in rows if r.lab_fault]
    if broken:
        return LAB_BROKE, (
            f"the lab broke {_episodes(len(broken))} ({_listed(broken)}), not the controller"
        )
    return None


def _listed(episodes: Sequence[int]) -> str:
    if len(episodes) == 1:
        return f"episode {episodes[0]}"
    more = ", ..." if len(episodes) > 10 else ""
    return "episodes " + ", ".join(str(e) for e in episodes[:10]) + more


def hide(evaluation: Evaluation) -> Evaluation:
    """A held-out evaluation as everyone but the operator sees it before its suite
    version is retired: its aggregate alone, once every episode has ended; while it
    runs, its status but no progress (each episode's end, seen as it happens, would time
    it); never its rows, their timings or its compute time."""
    ended = evaluation.status.ended
    counts: dict[str, Any] = {
        name: getattr(evaluation, name) if ended else None
        for name in ("done", "running", "queued", "successes", "errors")
    }
    if ended:
        counts.update(running=0, queued=0)
    return evaluation.model_copy(
        update={
            **counts,
            "mean_reward": evaluation.mean_reward if ended else None,
            "reward_interval": evaluation.reward_interval if ended else None,
            "compute_seconds": None,
            "verified_elsewhere": evaluation.verified_elsewhere if ended else None,
            "rows": [],
            "hidden": True,
            # which episodes: theirs to know once the suite version is retired
            "partial_reason": _counted(evaluation.partial_reason),
            "reproduced": _counted(evaluation.reproduced),
        }
    )


def _counted(said: str | None) -> str | None:
    """A verdict without the episodes it names ("diverged: 18 of 20 episodes identical;
    episodes 3, 9 differ" -> its first part)."""
    if said is None:
        return None
    return said.split(" (")[0].split(";")[0]


def episodes_sha256(rows: Sequence[EpisodeRow]) -> str:
    """The digest a held-out evaluation's statement commits to its episodes by: sha256
    of their canonical JSON (``{episode, trial, seed, status, outcome, reward,
    data_digest}`` each, in the suite's order, keys sorted, no spaces). Anyone can
    recompute it from the rows once the suite version is retired; nobody can recover
    the rows from it (each data digest is 256 bits no one has seen)."""
    listed = [r.stated() for r in rows]
    text = json.dumps(listed, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()


def statement(evaluation: Evaluation, finished: float) -> dict[str, Any]:
    """What the lab vouches for when every episode of an evaluation has ended: the
    commit, the suite and its version, whether it is partial, its successes over its
    episodes, and its episodes: listed (trial, seed, outcome, reward, data digest) for a
    public suite; for a held-out one, only committed to by ``episodes_sha256`` (the
    signature is public, the episodes are not). ``evaluation`` is the whole record,
    rows and seeds included."""
    said: dict[str, Any] = {
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
        "partial": evaluation.partial,
        "episodes": evaluation.episodes,
        "successes": evaluation.successes,
        "success_rate": evaluation.success_rate,
        "episodes_sha256": episodes_sha256(evaluation.rows),
        "finished": dt.datetime.fromtimestamp(finished, dt.UTC).isoformat(),
    }
    if not evaluation.held_out:
        said["rows"] = [r.stated() for r in evaluation.rows]
    return said


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
    """A commit's row on a suite's leaderboard: its first evaluation of the suite version
    that the lab did not break (``leaderboard``)."""

    model_config = ConfigDict(frozen=True)

    rank: int | None = Field(description="None: listed, not ranked (see note)")
    evaluation: int
    repository: str
    commit: str
    submitter: str = Field(description="who submitted that evaluation (never a rerunner)")
    episodes: int
    success_rate: float
    success_interval: tuple[float, float]
    mean_reward: float | None
    reward_interval: tuple[float, float] | None
    verified: bool = Field(description="the lab's own replay verified every episode")
    reproducible: bool | None = Field(
        default=None,
        description="its reruns: all reproduced it bit for bit (true), one diverged (false),"
        " none yet (null)",
    )
    tie: bool = Field(description="its success interval overlaps the ranked row above's")
    note: str | None = Field(default=None, description="why it is unranked, or marked")


def leaderboard(evaluations: Sequence[Evaluation]) -> list[LeaderRow]:
    """Each commit's row: its first evaluation (by submission) of ``evaluations`` that
    is not a rerun and that the lab did not break, never its best. Verified rows are
    ranked by success rate then mean reward; rows not (yet) verified follow, unranked.

    A commit whose first evaluation still runs has no row yet; one whose first
    evaluation its submitter cancelled has none at all (cancelling and resubmitting buys
    nothing). Reruns never replace a row: a rerun that diverged marks it not
    reproducible."""
    originals: dict[str, list[Evaluation]] = {}
    reruns: dict[int, list[Evaluation]] = {}
    for e in sorted(evaluations, key=lambda e: e.id):
        if e.rerun_of is None:
            originals.setdefault(e.commit, []).append(e)
        else:
            reruns.setdefault(e.rerun_of, []).append(e)
    chosen = [c for c in (_first(found) for found in originals.values()) if c is not None]
    ranked = sorted((e for e in chosen if e.verified), key=_rank_key)
    apart = sorted((e for e in chosen if not e.verified), key=_rank_key)
    rows: list[LeaderRow] = []
    for e in ranked:
        above = rows[-1] if rows else None
        rows.append(_row(e, reruns.get(e.id, []), len(rows) + 1, above, None))
    for e in apart:
        rows.append(_row(e, reruns.get(e.id, []), None, None, "not ranked: " + _unverified(e)))
    return rows


def _first(found: Sequence[Evaluation]) -> Evaluation | None:
    """A commit's evaluation that stands as its row, if any yet."""
    for e in found:
        if not e.status.ended:
            return None  # the first one that counts is still running
        if e.partial_cause == LAB_BROKE:
            continue  # not the controller's doing: the next one counts
        if e.partial or e.success_rate is None:
            return None  # cancelled: the commit is off this suite version's board
        return e
    return None


def _row(
    e: Evaluation,
    reruns: Sequence[Evaluation],
    rank: int | None,
    above: LeaderRow | None,
    note: str | None,
) -> LeaderRow:
    assert e.success_rate is not None and e.success_interval is not None
    ended = [r for r in reruns if r.status.ended and r.reproduced]
    diverged = [r for r in ended if not (r.reproduced or "").startswith("reproduced")]
    reproducible = None if not ended else not diverged
    if diverged:
        marked = f"not reproducible: rerun {diverged[0].id} diverged"
        note = f"{note}; {marked}" if note else marked
    return LeaderRow(
        rank=rank,
        evaluation=e.id,
        repository=e.repository,
        commit=e.commit,
        submitter=e.submitter,
        episodes=e.episodes,
        success_rate=e.success_rate,
        success_interval=e.success_interval,
        mean_reward=e.mean_reward,
        reward_interval=e.reward_interval,
        verified=e.verified,
        reproducible=reproducible,
        tie=above is not None
        and Interval(*above.success_interval).overlaps(Interval(*e.success_interval)),
        note=note,
    )


def _unverified(e: Evaluation) -> str:
    return "its episodes' replays are not all verified yet (the lab replays every record)"


def _rank_key(e: Evaluation) -> tuple[float, float, int]:
    reward = e.score.mean_reward
    return (
        -(e.score.success_rate or 0.0),
        -(reward if reward is not None else float("-inf")),
        e.id,
    )


def _pair(interval: Interval | None) -> tuple[float, float] | None:
    return (interval.low, interval.high) if interval is not None else None
