"""``labd evaluate``: score a commit on a task's fixed suite of episodes.

    labd evaluate REPO_URL [--ref REF] [--task TASK] [--suite dev] [--wait]
                  [--min-success RATE] [--json]
    labd evaluate REPO_URL --benchmark NAME [--suite SUITE] [--ref REF] [--wait]
                  [--min-iqm X] [--json]
    labd cancel --evaluation ID
    labd evaluations [--task T] [--suite S] [--repo URL] [--commit SHA] [--user U]
                     [--limit N] [--json]

``evaluate`` queues one trial per episode of the suite (``repository.evaluation``) and,
with ``--wait``, prints its progress on stderr until every episode has ended, then the
success rate with its 95 % interval. ``--min-success`` makes it a gate in a repository's
own CI, and waits as ``--wait`` does (saying so once on stderr): a gate that queued and
exited 0 would pass having checked nothing. Its last line on stderr says how the gate
went, and so does the exit code: 0 passed (a success rate of at least RATE), 1 failed
(below it), 4 cancelled, 3 partial (the lab broke an episode, so the score is not the
controller's), and the usual codes for errors (``labd.commands.common``). A held-out
evaluation's score is shown only once it has ended: it is gated then, like any other.
``labd cancel --evaluation ID`` (``cancel``) and ``labd rerun COMMIT --evaluations``
(``rerun``) are here too.

``--benchmark NAME`` evaluates the commit on every task of a benchmark instead (a
benchmark run, ``repository.benchmark_run``): one evaluation per task, followed as one,
scored by the IQM of every episode's normalized score. ``--min-iqm X`` is its gate, as
``--min-success`` is an evaluation's, with the same exit codes; a run one of whose
evaluations was cancelled or is partial exits as that evaluation would.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Iterator
from typing import Any

from labd.api.models import EvaluationPage, EvaluationView
from labd.commands.common import (
    REPOSITORY_HELP,
    ExitCode,
    emit,
    fail,
    repository_arg,
    server_options,
    worst,
)
from repository.benchmark_run import BenchmarkRun
from repository.errors import ArchiveError
from repository.stats import MIN_BOOTSTRAP
from repository.trial import Status
from scheduler.client import ApiClient
from scheduler.errors import RemoteError

POLL = 2.0  # seconds between looks at a running evaluation
REPLAYS = 120.0  # seconds to wait, after the last episode, for the replays' verdicts
VERIFYING = " to verify them"
GATE_WAITS = "labd evaluate: --min-success waits for every episode, as --wait does"
IQM_WAITS = "labd evaluate: --min-iqm waits for every episode, as --wait does"


class RunView(BenchmarkRun):
    """A benchmark run as ``GET /api/benchmark-runs/{id}`` serves it (the API's
    ``BenchmarkRunView``, whose module loads the web server)."""

    url: str


def add_parser(commands: Any) -> None:
    p = commands.add_parser(
        "evaluate", help="score a commit on a task's suite of episodes, with its uncertainty"
    )
    p.add_argument("repository", metavar="REPO_URL", type=repository_arg, help=REPOSITORY_HELP)
    p.add_argument("--ref", help="branch, tag or commit (default: the repository's HEAD)")
    p.add_argument("--task", help="the task (default: the one the repository's lab.toml names)")
    p.add_argument(
        "--benchmark",
        metavar="NAME",
        help="every task of this benchmark instead of one task (default: one task;"
        " `labd tasks` lists the benchmarks)",
    )
    p.add_argument(
        "--suite",
        help="the task's suite of episodes (default: dev; with --benchmark, each task's own;"
        " `labd tasks` lists them)",
    )
    p.add_argument(
        "--wait",
        action="store_true",
        help="wait for every episode, printing progress on stderr (default: no)",
    )
    p.add_argument(
        "--min-success",
        type=rate,
        metavar="RATE",
        help="a gate: wait (as --wait does), then exit 1 when the success rate is below RATE,"
        " a fraction (0.8) or a percentage (80%%) (default: no gate)",
    )
    p.add_argument(
        "--min-iqm",
        type=fraction,
        metavar="X",
        help="a benchmark run's gate: wait (as --wait does), then exit 1 when the IQM of its"
        " normalized scores is below X, from 0 to 1 (default: no gate)",
    )
    server_options(p, write=True)

    p = commands.add_parser("evaluations", help="list evaluations, newest first")
    p.add_argument("--task", help="only this task's (default: all)")
    p.add_argument("--suite", help="only this suite's (default: all)")
    p.add_argument(
        "--repo", type=repository_arg, help="only this repository URL's or folder's (default: all)"
    )
    p.add_argument("--commit", help="only this commit's, its 40 digits (default: all)")
    p.add_argument("--user", help="only this submitter's (default: everyone's)")
    p.add_argument("--limit", type=int, default=20, help="how many (default: %(default)s)")
    server_options(p)


def rate(text: str) -> float:
    """A success rate from the command line: ``0.8`` or ``80%``."""
    try:
        value = float(text[:-1]) / 100 if text.endswith("%") else float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a rate (0.8, or 80%)") from None
    if not 0.0 <= value <= 1.0:
        raise argparse.ArgumentTypeError(f"{text!r}: a rate is from 0 to 1 (0% to 100%)")
    return value


def fraction(text: str) -> float:
    """A normalized score from the command line: a number from 0 to 1."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number (0.5)") from None
    if not 0.0 <= value <= 1.0:
        raise argparse.ArgumentTypeError(f"{text!r}: a normalized score is from 0 to 1")
    return value


def _misused(args: argparse.Namespace) -> str | None:
    """What is wrong with ``labd evaluate``'s options together, if anything."""
    if args.command != "evaluate":
        return None
    if args.benchmark is not None and args.task is not None:
        return "--benchmark and --task are exclusive: a benchmark names its own tasks"
    if args.benchmark is not None and args.min_success is not None:
        return "--min-success gates one evaluation; a benchmark run's gate is --min-iqm"
    if args.benchmark is None and args.min_iqm is not None:
        return "--min-iqm gates a benchmark run: it needs --benchmark (one task's is --min-success)"
    return None


def main(args: argparse.Namespace) -> int:
    if (wrong := _misused(args)) is not None:
        return fail(args, wrong)
    try:
        with ApiClient(args.server, getattr(args, "token", None)) as client:
            if args.command == "evaluations":
                return _list(client, args)
            if args.benchmark is not None:
                return _benchmark(client, args)
            return _evaluate(client, args)
    except (RemoteError, ArchiveError) as err:
        return fail(args, str(err))


def _evaluate(client: ApiClient, args: argparse.Namespace) -> int:
    """Queue the evaluation; with ``--wait`` or a gate, follow it to its end, then say
    how the gate went in one line on stderr. A gate implies waiting: a score cannot be
    checked before it exists, and a CI job that forgot ``--wait`` must not pass having
    checked nothing."""
    waits = args.wait or args.min_success is not None
    if waits and not args.wait:
        print(GATE_WAITS, file=sys.stderr, flush=True)
    body = {
        "repository": args.repository,
        "ref": args.ref,
        "task": args.task,
        "suite": args.suite or "dev",
    }
    evaluation = client.post("/api/evaluations", EvaluationView, json=body)
    print(_queued(evaluation), file=sys.stderr, flush=True)
    if not waits:
        emit(args, evaluation.model_dump(mode="json"), lambda: _lines(evaluation))
        return ExitCode.SUCCESS
    evaluation = _follow(client, evaluation)
    emit(args, evaluation.model_dump(mode="json"), lambda: _lines(evaluation))
    code, said = gate(evaluation, args.min_success)
    if said is not None:
        print(said, file=sys.stderr, flush=True)
    return code


def _follow(client: ApiClient, evaluation: EvaluationView) -> EvaluationView:
    """Poll until every episode has ended and every record's replay has its verdict (a
    worker replays a record after filing it; at most ``REPLAYS`` seconds more), printing
    a line on stderr when it moves."""
    said = ""
    ended: float | None = None
    while True:
        if evaluation.status.ended:
            ended = ended or time.monotonic()
        last = ended is not None and (
            not _replaying(evaluation) or time.monotonic() - ended > REPLAYS
        )
        line = _progress(evaluation)
        if line != said and not (last and said.endswith(VERIFYING)):
            print(line, file=sys.stderr, flush=True)
            said = line
        if last:
            return evaluation
        time.sleep(POLL)
        evaluation = client.get(f"/api/evaluations/{evaluation.id}", EvaluationView)


def _replaying(e: EvaluationView) -> int:
    """Episodes with a record whose replay has no verdict yet (a hidden evaluation's
    rows are not shown: all of them until it is verified)."""
    if e.hidden:
        return 0 if e.verified else e.episodes
    return sum(r.data_digest is not None and r.verified is None for r in e.rows)


def gate(e: EvaluationView, min_success: float | None) -> tuple[ExitCode, str | None]:
    """The exit code of an evaluation followed to its end, and the line that says why
    (None for a whole evaluation when no gate was asked): passed, failed, or not checked,
    since a cancelled or partial evaluation has no score to gate on. A held-out
    evaluation is gated like any other, on the score it shows once it has ended."""
    unchecked = "" if min_success is None else "gate not checked: "
    if e.status is Status.CANCELLED:
        return ExitCode.CANCELLED, f"{unchecked}evaluation {e.id} was {_cancelled(e)}"
    if e.partial:  # the lab broke an episode: the score is not the controller's
        return ExitCode.ERROR, (
            f"{unchecked}evaluation {e.id} is partial: {e.partial_reason}; evaluate again"
        )
    s = e.score
    held = ", held out" if e.held_out else ""
    if s.success_rate is None:  # ended, yet no score shown: nothing to pass
        return ExitCode.FAIL, f"{unchecked}evaluation {e.id}{held} shows no score"
    if min_success is None:
        return ExitCode.SUCCESS, None
    rate, bound = _percents(s.success_rate, min_success)
    over = f"(evaluation {e.id}{held}: {s.successes} of {s.episodes} episodes succeeded)"
    if s.success_rate >= min_success:
        return ExitCode.SUCCESS, f"gate passed: {rate} ≥ {bound} {over}"
    return ExitCode.FAIL, f"gate failed: {rate} is below --min-success {bound} {over}"


def _cancelled(e: EvaluationView) -> str:
    """How a cancelled evaluation was cancelled, after its number: "cancelled by its
    submitter (17 episodes unfinished)", or "cancelled: 2 episodes cancelled (4, 7)"."""
    reason = e.partial_reason or "cancelled"
    return reason if reason.startswith("cancelled") else f"cancelled: {reason}"


def _percents(rate: float, bound: float) -> tuple[str, str]:
    """Two rates as percentages with the fewest decimals that keep them apart (79.5 %
    is below 80 %, never "80 % is below 80 %")."""
    for digits in range(4):
        a, b = f"{100 * rate:.{digits}f}", f"{100 * bound:.{digits}f}"
        if (a == b) == (rate == bound):
            break
    return f"{a} %", f"{b} %"


def _queued(e: EvaluationView) -> str:
    held = ", held out" if e.held_out else ""
    return (
        f"evaluation {e.id}: {e.repository}@{e.commit[:12]} on {e.task} suite {e.suite}"
        f" (version {e.suite_version}{held}), {e.score.episodes} episodes queued; {e.page}"
    )


def _progress(e: EvaluationView) -> str:
    s = e.score
    if e.status.ended and (left := _replaying(e)):
        return f"evaluation {e.id}: {e.status}; replaying {_episodes(left)}{VERIFYING}"
    if s.done is None or s.successes is None:  # held out: no progress until it has ended
        return f"evaluation {e.id}: {e.status} (held out: its score is shown when it has ended)"
    so_far = f"; {s.successes} of {s.done} succeeded ({s.successes / s.done:.0%})" if s.done else ""
    return (
        f"evaluation {e.id}: {s.done}/{s.episodes} done, {s.running} running,"
        f" {s.queued} queued{so_far}"
    )


def _episodes(n: int) -> str:
    return f"{n} episode" if n == 1 else f"{n} episodes"


def _percent(value: float) -> str:
    return f"{100 * value:.0f} %"


def _lines(e: EvaluationView) -> Iterator[str]:
    s = e.score
    partial = f" (partial: {e.partial_reason})" if e.partial else ""
    yield (
        f"evaluation {e.id}: {e.repository}@{e.commit[:12]} on {e.task} suite {e.suite}"
        f" version {e.suite_version}: {e.status}{partial}"
    )
    if s.success_rate is not None and s.success_interval is not None:
        low, high = s.success_interval
        done, successes, errors = s.done or 0, s.successes or 0, s.errors or 0
        unfinished = f", {s.episodes - done} cancelled" if done < s.episodes else ""
        yield (
            f"  success rate {_percent(s.success_rate)} (95 % interval {_percent(low)} to"
            f" {_percent(high)}) over {s.episodes} episodes: {successes} success,"
            f" {done - successes - errors} fail, {errors} error{unfinished}"
        )
    elif s.done is None:
        yield "  held out: its score is shown when every episode has ended"
    else:
        yield f"  {s.done} of {s.episodes} episodes ended ({s.queued} queued, {s.running} running)"
    if s.mean_reward is not None and s.reward_interval is not None:
        low, high = s.reward_interval
        yield f"  mean reward {s.mean_reward:.4g} (95 % interval {low:.4g} to {high:.4g})"
    elif s.mean_reward is not None:
        yield (
            f"  mean reward {s.mean_reward:.4g} (no 95 % interval: the rewards are all alike,"
            f" or fewer than {MIN_BOOTSTRAP})"
        )
    unverified = [r.episode for r in e.rows if not r.verified]
    if s.verified:
        yield "  verified: the lab's replay of every episode reproduced its record"
    elif e.status.ended and e.hidden:
        yield "  not verified: not every episode's replay verified (yet)"
    elif e.status.ended:
        yield f"  not verified: {_episodes(len(unverified))} without a verified replay"
    if s.verified_elsewhere is not None:
        yield f"  verified on another machine: {s.verified_elsewhere} of {s.episodes}"
    if e.reproduced:
        yield f"  {e.reproduced}"
    if e.signature:
        yield f"  signed by the lab ({e.signature.get('key')})"
    yield f"  {e.page}"


def _benchmark(client: ApiClient, args: argparse.Namespace) -> int:
    """Queue a benchmark run; with ``--wait`` or ``--min-iqm``, follow it to its end as
    ``_evaluate`` follows an evaluation, then say how the gate went."""
    waits = args.wait or args.min_iqm is not None
    if waits and not args.wait:
        print(IQM_WAITS, file=sys.stderr, flush=True)
    body = {
        "repository": args.repository,
        "ref": args.ref,
        "benchmark": args.benchmark,
        "suite": args.suite,  # None: each task's own
    }
    run = client.post("/api/benchmark-runs", RunView, json=body)
    print(_run_queued(run), file=sys.stderr, flush=True)
    if not waits:
        emit(args, run.model_dump(mode="json"), lambda: _run_lines(run))
        return ExitCode.SUCCESS
    run, evaluations = _follow_run(client, run)
    emit(args, run.model_dump(mode="json"), lambda: _run_lines(run))
    code, said = run_gate(run, evaluations, args.min_iqm)
    if said is not None:
        print(said, file=sys.stderr, flush=True)
    return code


def _follow_run(client: ApiClient, run: RunView) -> tuple[RunView, list[EvaluationView]]:
    """Poll until the run has ended and every record's replay has its verdict (at most
    ``REPLAYS`` seconds more), printing a line on stderr when it moves; the run, and its
    evaluations as they ended."""
    said = ""
    ended: float | None = None
    evaluations: list[EvaluationView] = []
    while True:
        if run.status.ended:
            ended = ended or time.monotonic()
            evaluations = [
                client.get(f"/api/evaluations/{t.evaluation}", EvaluationView)
                for t in run.evaluations
            ]
            run = client.get(f"/api/benchmark-runs/{run.id}", RunView)  # no older than they
        left = sum(_replaying(e) for e in evaluations)
        last = ended is not None and (not left or time.monotonic() - ended > REPLAYS)
        line = _run_progress(run, left)
        if line != said and not (last and said.endswith(VERIFYING)):
            print(line, file=sys.stderr, flush=True)
            said = line
        if last:
            return run, evaluations
        time.sleep(POLL)
        run = client.get(f"/api/benchmark-runs/{run.id}", RunView)


def run_gate(
    run: BenchmarkRun, evaluations: list[EvaluationView], min_iqm: float | None
) -> tuple[ExitCode, str | None]:
    """The exit code of a benchmark run followed to its end, and the line that says why
    (None for a whole run when no gate was asked). An evaluation of the run that was
    cancelled or is partial leaves the run with no score to gate on: the run exits as
    that evaluation would (the most serious of them, ``worst``)."""
    unchecked = "" if min_iqm is None else "gate not checked: "
    verdicts = [gate(e, None) for e in evaluations]
    code = worst(c for c, _ in verdicts)
    if code is not ExitCode.SUCCESS:
        said = next(line for c, line in verdicts if c is code)
        return code, f"{unchecked}benchmark run {run.id}: {said}"
    if run.status is Status.CANCELLED:  # no evaluation says so: said here
        return ExitCode.CANCELLED, f"{unchecked}benchmark run {run.id} was cancelled"
    if run.iqm is None:
        return ExitCode.FAIL, f"{unchecked}benchmark run {run.id} shows no IQM"
    if min_iqm is None:
        return ExitCode.SUCCESS, None
    iqm, bound = _apart(run.iqm, min_iqm)
    over = f"(benchmark run {run.id} on {run.benchmark}: {run.done} episodes)"
    if run.iqm >= min_iqm:
        return ExitCode.SUCCESS, f"gate passed: IQM {iqm} ≥ {bound} {over}"
    return ExitCode.FAIL, f"gate failed: IQM {iqm} is below --min-iqm {bound} {over}"


def _apart(value: float, bound: float) -> tuple[str, str]:
    """Two normalized scores with three decimals, or more where three print them alike."""
    for digits in range(3, 7):
        a, b = f"{value:.{digits}f}", f"{bound:.{digits}f}"
        if (a == b) == (value == bound):
            break
    return a, b


def _run_queued(run: RunView) -> str:
    return (
        f"benchmark run {run.id}: {run.repository}@{run.commit[:12]} on {run.benchmark},"
        f" {len(run.evaluations)} tasks, {run.episodes} episodes queued; {run.url}"
    )


def _run_progress(run: BenchmarkRun, replaying: int) -> str:
    if run.status.ended and replaying:
        return f"benchmark run {run.id}: {run.status}; replaying {_episodes(replaying)}{VERIFYING}"
    so_far = "" if run.status.ended else " so far"
    iqm = f"; IQM {run.iqm:.3f}{so_far}" if run.iqm is not None else ""
    return f"benchmark run {run.id}: {run.done}/{run.episodes} episodes done{iqm}"


def _scored(value: float | None, interval: tuple[float, float] | None) -> str:
    if value is None:
        return "none yet"
    if interval is None:
        return f"{value:.3f} (no 95 % interval: too few episodes, or all alike)"
    return f"{value:.3f} (95 % interval {interval[0]:.3f} to {interval[1]:.3f})"


def _run_lines(run: RunView) -> Iterator[str]:
    suite = f" suite {run.suite}" if run.suite else ""  # "": each task's own
    yield (
        f"benchmark run {run.id}: {run.repository}@{run.commit[:12]} on {run.benchmark}"
        f"{suite}: {run.status}"
    )
    width = max((len(t.task) for t in run.evaluations), default=0)
    for t in run.evaluations:
        yield (
            f"  {t.task:<{width}}  {_scored(t.normalized_mean, t.normalized_interval)}"
            f" over {t.done} of {t.episodes} episodes (evaluation {t.evaluation}, {t.status})"
        )
    if run.iqm is not None:
        mean, median = (
            _scored(run.mean, run.mean_interval),
            _scored(run.median, run.median_interval),
        )
        yield f"  IQM {_scored(run.iqm, run.iqm_interval)}, mean {mean}, median {median}"
    else:
        yield f"  no IQM yet ({run.done} of {run.episodes} episodes ended; one of each task needed)"
    unverified = [t.task for t in run.evaluations if not t.verified]
    if run.verified:
        yield "  verified: the lab's replay of every episode of every task reproduced its record"
    elif run.status.ended:
        yield f"  not verified: not every episode's replay verified ({', '.join(unverified)})"
    if run.signature:
        yield f"  signed by the lab ({run.signature.get('key')})"
    yield f"  {run.url}"


def rerun(client: ApiClient, args: argparse.Namespace) -> int:
    """``labd rerun COMMIT --evaluations``: rerun the commit's newest evaluation (every
    one with ``--all``) as new evaluations, episode by episode; with ``--wait``, one
    verdict each, and exit 0 only if every episode reproduced (5 if one diverged)."""
    page = client.get(
        "/api/evaluations", EvaluationPage, params={"commit": args.target, "limit": 200}
    )
    originals = [e for e in page.evaluations if e.rerun_of is None]
    if not originals:
        return fail(args, f"commit {args.target} has no evaluations to rerun")
    chosen = originals if args.all else originals[:1]
    made = [client.post(f"/api/evaluations/{e.id}/rerun", EvaluationView) for e in chosen]
    for e in made:
        print(
            f"evaluation {e.id} queued: a rerun of evaluation {e.rerun_of}; {e.page}",
            file=sys.stderr,
        )
    if args.wait:
        made = [_follow(client, e) for e in made]
    emit(
        args,
        [e.model_dump(mode="json") for e in made],
        lambda: [f"evaluation {e.id} (a rerun of {e.rerun_of}): {e.reproduced}" for e in made],
    )
    if not args.wait:
        return ExitCode.SUCCESS
    if any(e.status is Status.CANCELLED for e in made):
        return ExitCode.CANCELLED
    reproduced = all((e.reproduced or "").startswith("reproduced") for e in made)
    return ExitCode.SUCCESS if reproduced else ExitCode.DIVERGED


def cancel(client: ApiClient, args: argparse.Namespace) -> int:
    """``labd cancel --evaluation ID``: cancel its episodes still queued and stop those
    running (what finished is kept, and the evaluation is partial); exit 2 if it had
    already ended, as ``labd cancel TRIAL`` does."""
    path = f"/api/evaluations/{args.trial}"
    before = client.get(path, EvaluationView)
    e = before if before.status.ended else client.post(f"{path}/cancel", EvaluationView)
    if e.status is Status.CANCELLED and not before.status.ended:
        said = [f"evaluation {e.id} {_cancelled(e)}", f"  {e.page}"]
    elif not e.status.ended:
        said = [
            f"evaluation {e.id} is running: cancelling; the workers stop its running episodes"
            " within seconds",
            f"  follow it: {e.page}",
        ]
    else:
        return fail(args, f"evaluation {e.id} had already ended ({e.status}); nothing to cancel")
    emit(args, e.model_dump(mode="json"), lambda: said)
    return ExitCode.SUCCESS


def _list(client: ApiClient, args: argparse.Namespace) -> int:
    query = {
        "task": args.task,
        "suite": args.suite,
        "repository": args.repo,
        "commit": args.commit,
        "submitter": args.user,
        "limit": args.limit,
    }
    page = client.get(
        "/api/evaluations", EvaluationPage, params={k: v for k, v in query.items() if v}
    )

    def lines() -> Iterator[str]:
        if not page.evaluations:
            yield "no evaluations"
        for e in page.evaluations:
            s = e.score
            score = (
                f"{_percent(s.success_rate)} of {s.episodes}"
                if s.success_rate is not None
                else f"{s.done} of {s.episodes} ended"
                if s.done is not None
                else "held out, running"
            )
            yield (
                f"{e.id:>6}  {e.task} {e.suite}@{e.suite_version}  {e.commit[:12]}  "
                f"{e.status:<9} {score}{'  verified' if s.verified else ''}  {e.submitter}"
            )

    emit(args, page.model_dump(mode="json"), lines)
    return ExitCode.SUCCESS
