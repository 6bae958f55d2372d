"""The commands that talk to a running lab over its HTTP API.

    labd submit REPO_URL [--ref REF] [--task TASK] [--seed N] [--param NAME=VALUE] [--wait]
    labd trials [--repo URL] [--commit SHA] [--task T] [--status S] [--outcome O]
                [--kind K] [--user U] [--limit N] [--before ID]
    labd show TRIAL
    labd logs TRIAL [--stream stdout|stderr]
    labd download TRIAL [-o FILE]
    labd rerun COMMIT|TRIAL [--all] [--wait]
    labd rerun COMMIT --evaluations [--all] [--wait]   (labd.commands.evaluate)
    labd cancel TRIAL | --evaluation ID                (an evaluation: labd.commands.evaluate)
    labd export TRIAL --format F | --task T ... --format F   (labd.commands.export)
    labd tasks                  the tasks, then the benchmarks of the task packs
    labd status

Each takes ``--server URL`` (default ``$LABD_SERVER`` or http://127.0.0.1:8080) and
``--json``; those that write take ``--token`` (default ``$LABD_TOKEN``). Errors from
the server are printed as it words them. Exit codes are in ``labd.commands.common``.
A repository given as a path is the caller's: made absolute here, before it is sent
(``labd.commands.common.repository_arg``).
"""

from __future__ import annotations

import argparse
import re
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from labd.api.models import (
    CancelView,
    CommitView,
    LabStatus,
    TaskList,
    TrialDetail,
    TrialPage,
    WorkerView,
    task_list,
)
from labd.commands import evaluate
from labd.commands.common import (
    REPOSITORY_HELP,
    ExitCode,
    emit,
    exit_code,
    fail,
    param_option,
    repository_arg,
    server_options,
    worst,
)
from labd.sim import registry
from repository.benchmark import BenchmarkList
from repository.digests import readable_json
from repository.errors import ArchiveError, ManifestError
from repository.manifest import Manifest
from repository.trial import Kind, Outcome, Status
from repository.well_known import SIGNATURE_SIDECAR
from scheduler.client import ApiClient
from scheduler.errors import ApiRefused, RemoteError
from scheduler.states import Cancel

# the lab's refusal to cancel one episode alone (scheduler.errors.EpisodeOfEvaluation)
EPISODE = re.compile(r"is an episode of evaluation (\d+)")


def add_parser(commands: Any) -> None:
    p = commands.add_parser("submit", help="queue a trial of a repository at a ref")
    p.add_argument("repository", metavar="REPO_URL", type=repository_arg, help=REPOSITORY_HELP)
    p.add_argument("--ref", help="branch, tag or commit (default: the repository's HEAD)")
    p.add_argument(
        "--task",
        help="the task to run (default: the one the repository's lab.toml names;"
        " `labd tasks` lists them)",
    )
    p.add_argument("--seed", type=int, default=0, help="the episode's seed (default: 0)")
    param_option(p)
    p.add_argument("--wait", action="store_true", help="wait for the trial to end (default: no)")
    server_options(p, write=True)

    p = commands.add_parser("trials", help="list trials in the archive, newest first")
    p.add_argument(
        "--repo", type=repository_arg, help="only this repository URL or folder (default: all)"
    )
    p.add_argument("--commit", help="only this commit, or commits starting with these digits")
    p.add_argument("--task", help="only this task (default: all)")
    p.add_argument("--status", choices=[s.value for s in Status], help="only this status")
    p.add_argument("--outcome", choices=[o.value for o in Outcome], help="only this outcome")
    p.add_argument("--kind", choices=[k.value for k in Kind], help="trials or demonstrations")
    p.add_argument("--user", help="only this submitter's (default: everyone's)")
    p.add_argument("--limit", type=int, default=20, help="trials per page (default: 20)")
    p.add_argument("--before", type=int, help="the next page: the cursor a page printed")
    server_options(p)

    p = commands.add_parser("show", help="one trial: how it ended, what ran, its record")
    p.add_argument("trial", type=int, metavar="TRIAL", help="the trial's number")
    server_options(p)

    p = commands.add_parser("logs", help="print a trial's controller output")
    p.add_argument("trial", type=int, metavar="TRIAL", help="the trial's number")
    p.add_argument(
        "--stream",
        choices=["stdout", "stderr", "both"],
        default="both",
        help="which output (default: both, stdout first)",
    )
    server_options(p)

    p = commands.add_parser("download", help="download a trial's MCAP record")
    p.add_argument("trial", type=int, metavar="TRIAL", help="the trial's number")
    p.add_argument("-o", "--output", type=Path, help="the file (default: trial-N.mcap)")
    server_options(p)

    p = commands.add_parser("rerun", help="rerun a trial, or a commit's trials, to check them")
    p.add_argument("target", metavar="COMMIT|TRIAL", help="a trial number or a commit")
    p.add_argument(
        "--all", action="store_true", help="every trial of the commit (default: the newest)"
    )
    p.add_argument(
        "--evaluations",
        action="store_true",
        help="the commit's evaluations instead, every episode of each, one verdict each"
        " (default: its trials)",
    )
    p.add_argument("--wait", action="store_true", help="wait and print the verdicts")
    server_options(p, write=True)

    p = commands.add_parser("cancel", help="cancel a queued or running trial, or an evaluation")
    p.add_argument(
        "trial", type=int, metavar="ID", help="the trial's number (--evaluation: the evaluation's)"
    )
    p.add_argument(
        "--evaluation",
        action="store_true",
        help="ID is an evaluation's: cancel its episodes not yet ended; the finished ones are"
        " kept and it is partial (default: ID is a trial's)",
    )
    server_options(p, write=True)

    p = commands.add_parser(
        "tasks", help="the lab's tasks and their parameters, then its benchmarks"
    )
    p.add_argument(
        "--local",
        action="store_true",
        help="the tasks and benchmarks this machine's labd runs (its installed task plugins),"
        " without asking a lab",
    )
    server_options(p)

    p = commands.add_parser("status", help="the lab now: the queue and what workers run")
    server_options(p)


def main(args: argparse.Namespace) -> int:
    handler = COMMANDS[args.command]
    if args.command == "tasks" and args.local:
        return _show_tasks(task_list(), BenchmarkList(registry.benchmarks()), args)
    try:
        with ApiClient(args.server, getattr(args, "token", None)) as client:
            return int(handler(client, args))
    except (RemoteError, ArchiveError) as err:
        return fail(args, str(err))


def _submit(client: ApiClient, args: argparse.Namespace) -> int:
    body = {
        "repository": args.repository,
        "ref": args.ref,
        "task": args.task,
        "seed": args.seed,
        "params": dict(args.param),
    }
    row = client.post("/api/trials", TrialDetail, json=body)
    if not args.wait:
        emit(args, _json(row), lambda: _queued_lines(row))
        return ExitCode.SUCCESS
    if not args.json:
        print("\n".join(_queued_lines(row)), flush=True)
    [row] = wait(client, [row.id], progress=_stderr)
    emit(args, _json(row), lambda: _trial_lines(row))
    return exit_code(row.status, row.outcome)


def _trials(client: ApiClient, args: argparse.Namespace) -> int:
    query = {
        "repository": args.repo,
        "commit": args.commit,
        "task": args.task,
        "status": args.status,
        "outcome": args.outcome,
        "kind": args.kind,
        "user": args.user,
        "limit": args.limit,
        "before": args.before,
    }
    params = {k: v for k, v in query.items() if v is not None}
    page = client.get("/api/trials", TrialPage, params=params)
    emit(args, page.model_dump(mode="json"), lambda: _table(page))
    return ExitCode.SUCCESS


def _show(client: ApiClient, args: argparse.Namespace) -> int:
    row = client.get(f"/api/trials/{args.trial}", TrialDetail)
    emit(args, _json(row), lambda: _trial_lines(row, full=True))
    return ExitCode.SUCCESS


def _logs(client: ApiClient, args: argparse.Namespace) -> int:
    row = client.get(f"/api/trials/{args.trial}", TrialDetail)
    streams = ["stdout", "stderr"] if args.stream == "both" else [args.stream]
    texts = {}
    for stream in streams:
        if stream in row.logs:
            texts[stream] = client.request("GET", row.logs[stream]).text
    if not texts:
        return fail(args, f"trial {row.id} has no controller output ({_state(row)})")

    def lines() -> Iterator[str]:
        for stream, text in texts.items():
            if len(texts) > 1:
                yield f"==> {stream} <=="
            yield text.rstrip("\n")

    emit(args, texts, lines)
    return ExitCode.SUCCESS


def _download(client: ApiClient, args: argparse.Namespace) -> int:
    """The record, and beside it the lab's signature of it (for ``labd verify``)."""
    row = client.get(f"/api/trials/{args.trial}", TrialDetail)
    dest = args.output or Path(f"trial-{args.trial}.mcap")
    digest = row.mcap.digest if row.mcap else None
    size = client.download(f"/api/trials/{args.trial}/data.mcap", dest, digest=digest)
    signed = None
    if row.signature is not None:
        signed = dest.with_name(dest.name + SIGNATURE_SIDECAR)
        signed.write_bytes(readable_json(row.signature))
    info = {"path": str(dest), "size": size, "signature": str(signed) if signed else None}
    said = [f"{dest} ({size:,} bytes)"] + ([f"{signed} (the lab's signature)"] if signed else [])
    emit(args, info, lambda: said)
    return ExitCode.SUCCESS


def _rerun(client: ApiClient, args: argparse.Namespace) -> int:
    if args.evaluations:
        return evaluate.rerun(client, args)
    target = args.target
    if target.isdigit() and len(target) < 7:
        originals = [int(target)]
    else:
        page = client.get(f"/api/commits/{target}", CommitView)
        originals = [t.id for t in page.trials]
        if not originals:
            return fail(args, f"commit {target} has no trials to rerun")
        originals = originals if args.all else originals[:1]
    made = [client.post(f"/api/trials/{t}/rerun", TrialDetail) for t in originals]
    if not args.wait:
        lines = [line for row in made for line in _queued_lines(row)]
        emit(args, [_json(r) for r in made], lambda: lines)
        return ExitCode.SUCCESS
    if not args.json:
        for row in made:
            print(f"trial {row.id} queued: a rerun of trial {row.rerun_of}", flush=True)
    done = wait(client, [row.id for row in made], progress=_stderr)
    emit(args, [_json(r) for r in done], lambda: [_verdict_line(row) for row in done])
    return worst(_rerun_code(row) for row in done)


def _rerun_code(row: TrialDetail) -> ExitCode:
    if row.reproduced:
        return ExitCode.SUCCESS
    if row.status is Status.FINISHED and row.reproduced is False:
        return ExitCode.DIVERGED
    return worst([exit_code(row.status, row.outcome), ExitCode.DIVERGED])


def _cancel(client: ApiClient, args: argparse.Namespace) -> int:
    if args.evaluation:
        return evaluate.cancel(client, args)
    try:
        answer = client.post(f"/api/trials/{args.trial}/cancel", CancelView)
    except ApiRefused as err:
        episode = EPISODE.search(err.message) if err.status == 409 else None
        if episode is None:
            raise
        return fail(args, f"{err.message}: labd cancel --evaluation {episode.group(1)}")
    row = answer.trial
    if answer.done is Cancel.CANCELLED:
        emit(args, _json(row), lambda: [f"trial {row.id} cancelled: {row.reason}"])
        return ExitCode.SUCCESS
    if answer.done is Cancel.STOPPING:
        text = f"trial {row.id} is running: cancelling; its worker stops it within seconds"
        emit(args, _json(row), lambda: [text, f"  follow it: labd show {row.id}"])
        return ExitCode.SUCCESS
    return fail(args, f"trial {row.id} had already ended ({_state(row)}); nothing to cancel")


def _tasks(client: ApiClient, args: argparse.Namespace) -> int:
    listing = client.get("/api/tasks", TaskList)
    return _show_tasks(listing, client.get("/api/benchmarks", BenchmarkList), args)


def _show_tasks(listing: TaskList, benchmarks: BenchmarkList, args: argparse.Namespace) -> int:
    """The tasks, then the benchmarks (name, how many tasks, doc); under --json, the
    task list's body with a ``benchmarks`` key (``GET /api/benchmarks``'s list)."""

    def lines() -> Iterator[str]:
        for task in listing.tasks:
            yield f"{task.name} (version {task.version})"
            yield f"  {task.doc.strip().splitlines()[0] if task.doc.strip() else ''}"
            for name, param in task.params.items():
                yield f"  --param {name}=...  {param.describe}"
            for suite in task.suites:
                kind = "held out" if suite.held_out else "public seeds"
                yield (
                    f"  --suite {suite.name}  version {suite.version}, {suite.episodes}"
                    f" episodes, {kind}: {suite.doc}"
                )
        for left in listing.problems:
            yield f"left out: the task plugin {left.plugin}: {left.problem}"
        if benchmarks.root:
            yield ""
            yield "benchmarks (each task on one suite; GET /api/benchmarks/NAME says which):"
        for benchmark in benchmarks.root:
            count = f"{len(benchmark.tasks)} task{'s' if len(benchmark.tasks) != 1 else ''}"
            yield f"{benchmark.name} ({count})"
            yield f"  {benchmark.doc.strip().splitlines()[0]}"

    emit(
        args,
        {**listing.model_dump(mode="json"), "benchmarks": benchmarks.model_dump(mode="json")},
        lines,
    )
    return ExitCode.SUCCESS


def _status(client: ApiClient, args: argparse.Namespace) -> int:
    now = client.get("/api/status", LabStatus)

    def lines() -> Iterator[str]:
        own = f"{now.local_workers} worker{'s' if now.local_workers != 1 else ''} in the lab"
        yield f"labd {now.version}: {now.queued} queued, {len(now.running)} running; {own}"
        for w in now.running:
            stage = f", {w.stage} for {w.stage_seconds:.0f} s" if w.stage else ""
            ran = f"{w.running_seconds:.0f} s" if w.running_seconds is not None else "?"
            yield f"  trial {w.trial} ({w.task}) on {w.worker}: running {ran}{stage}"
        for h in now.workers:
            if h.state != "ok":
                yield f"  worker {h.worker}: {h.state.upper()}: {h.detail}"

    emit(args, now.model_dump(mode="json"), lines)
    return ExitCode.SUCCESS


COMMANDS: dict[str, Callable[[ApiClient, argparse.Namespace], int]] = {
    "submit": _submit,
    "trials": _trials,
    "show": _show,
    "logs": _logs,
    "download": _download,
    "rerun": _rerun,
    "cancel": _cancel,
    "tasks": _tasks,
    "status": _status,
}


def wait(
    client: ApiClient,
    trial_ids: list[int],
    poll: float = 1.0,
    progress: Callable[[str], None] | None = None,
) -> list[TrialDetail]:
    """Wait until every trial has ended; ``progress`` is told each trial's state in a
    line whenever it changes (its place in the queue, then its worker's stage)."""
    pending = set(trial_ids)
    rows: dict[int, TrialDetail] = {}
    said: dict[int, str] = {}
    while pending:
        running: dict[int, WorkerView] | None = None
        for trial_id in sorted(pending):
            row = client.get(f"/api/trials/{trial_id}", TrialDetail)
            if row.status.ended:
                rows[trial_id] = row
                pending.discard(trial_id)
                continue
            if progress is None:
                continue
            if row.status is Status.RUNNING and running is None:
                running = {w.trial: w for w in client.get("/api/status", LabStatus).running}
            line = _progress(row, (running or {}).get(trial_id))
            if said.get(trial_id) != line:
                said[trial_id] = line
                progress(line)
        if pending:
            time.sleep(poll)
    return [rows[t] for t in trial_ids]


def _progress(row: TrialDetail, worker: WorkerView | None) -> str:
    """Where a trial that has not ended is, in a line."""
    if row.status is Status.QUEUED:
        ahead = row.queued_ahead
        if ahead is None:
            return f"trial {row.id}: queued"
        return f"trial {row.id}: queued, " + (
            "next" if ahead == 0 else f"{ahead} submitted before it still waiting"
        )
    where = f" on {worker.worker}" if worker is not None else ""
    stage = f": {worker.stage}" if worker is not None and worker.stage else ""
    return f"trial {row.id}: running{where}{stage}"


def _stderr(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


# -- printing ----------------------------------------------------------------------------


def _json(row: TrialDetail) -> dict[str, Any]:
    return row.model_dump(mode="json")


def _state(row: TrialDetail) -> str:
    return f"{row.status.value}: {row.outcome.value}" if row.outcome else row.status.value


def headline(row: TrialDetail) -> str:
    """The first thing said of a trial: its outcome once finished, else its status."""
    if row.outcome is not None:
        return f"trial {row.id}: {row.outcome.value.upper()}: {row.reason}"
    return f"trial {row.id}: {row.status.value}: {row.reason}"


def _queued_lines(row: TrialDetail) -> Iterator[str]:
    ref = f" ({row.ref})" if row.ref and row.ref != row.commit else ""
    what = f"a rerun of trial {row.rerun_of}" if row.rerun_of else row.task
    yield f"trial {row.id} queued: {what}"
    yield f"  {row.repository} @ {row.commit}{ref}"
    yield f"  seed {row.seed}" + (f", params {_params(row.params)}" if row.params else "")
    if row.data:
        yield f"  learns from {_data(row)}"
    yield f"  follow it: labd show {row.id}, or {row.page}"


def _data(row: TrialDetail) -> str:
    """The pinned records, in words: how many, which, and the first digests."""
    records = row.data or []
    ids = ", ".join(str(p.trial) for p in records[:12]) + (", ..." if len(records) > 12 else "")
    return f"{len(records)} pinned records (trials {ids})"


def _trial_lines(row: TrialDetail, full: bool = False) -> Iterator[str]:
    yield headline(row)
    yield f"  page       {row.page}"
    ref = f" ({row.ref})" if row.ref and row.ref != row.commit else ""
    yield f"  repository {row.repository}"
    yield f"  commit     {row.commit}{ref}"
    params = f", params {_params(row.params)}" if row.params else ""
    yield f"  task       {row.task}, seed {row.seed}{params}"
    yield f"  submitter  {row.submitter}, submitted {_time(row.created)}"
    if row.rerun_of:
        yield f"  rerun of   trial {row.rerun_of}: {row.verdict or 'not compared yet'}"
    if row.data:
        yield f"  learns     {_data(row)}"
    if row.metrics:
        yield "  metrics    " + ", ".join(f"{k}={_fmt(v)}" for k, v in row.metrics.items())
    if row.manifest_digest:
        yield f"  manifest   sha256:{row.manifest_digest}"
    if row.data_digest:
        yield f"  data       sha256:{row.data_digest}"
    if row.mcap:
        yield f"  record     {row.mcap.url} ({row.mcap.size or 0:,} bytes)"
    if row.logs:
        yield f"  logs       labd logs {row.id}"
    if full and row.manifest:
        try:
            versions = Manifest.from_json(row.manifest).versions.to_json()
        except ManifestError as err:
            yield f"  versions   unknown: the manifest cannot be read ({err})"
        else:
            yield "  versions   " + ", ".join(f"{k} {v}" for k, v in versions.items())


def _verdict_line(row: TrialDetail) -> str:
    """A rerun's verdict; one that did not reproduce says how the rerun ended, and why
    (a rerun that broke made no record to compare: its reason is what to act on)."""
    said = f"trial {row.id} (rerun of {row.rerun_of})"
    if row.reproduced:
        return f"{said}: {row.verdict}"
    if row.verdict and row.outcome is not None:
        return f"{said}: {row.verdict}; it ended {row.outcome.value.upper()}: {row.reason}"
    return f"{said}: {_state(row)}: {row.reason}"


def _table(page: TrialPage) -> Iterator[str]:
    rows = page.trials
    if not rows:
        yield "no trials"
        return
    yield (
        f"{'ID':>6}  {'OUTCOME':<9}  {'REWARD':>8}  {'TASK':<12}  {'COMMIT':<12}  {'SEED':>5}  "
        f"{'USER':<10}  REPOSITORY"
    )
    for r in rows:
        outcome = r.outcome.value if r.outcome else r.status.value
        reward = _fmt(r.reward) if r.reward is not None else "-"
        rerun = f"  (rerun of {r.rerun_of}: {r.verdict or '...'})" if r.rerun_of else ""
        yield (
            f"{r.id:>6}  {outcome:<9}  {reward:>8}  {r.task:<12}  {r.commit[:12]:<12}  "
            f"{r.seed:>5}  {r.submitter[:10]:<10}  {r.repository}{rerun}"
        )
    if page.next:
        yield f"more: --before {page.next}"


def _time(moment: Any) -> str:
    return moment.strftime("%Y-%m-%d %H:%M:%S UTC") if moment else "-"


def _params(params: dict[str, Any]) -> str:
    return " ".join(f"{k}={v}" for k, v in params.items())


def _fmt(value: Any) -> str:
    return f"{value:.4g}" if isinstance(value, float) else str(value)
