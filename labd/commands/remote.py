"""The commands that talk to a running lab over its HTTP API.

    labd submit REPO_URL [--ref REF] --task TASK [--seed N] [--param NAME=VALUE] [--wait]
    labd trials [--repo URL] [--commit SHA] [--task T] [--status S] [--user U] [--limit N]
    labd show TRIAL
    labd download TRIAL [-o FILE]
    labd rerun COMMIT|TRIAL [--all] [--wait]
    labd cancel TRIAL
    labd export TRIAL --format lerobot|parquet [-o DIR]

Each takes ``--server URL`` (default ``$LABD_SERVER`` or http://127.0.0.1:8080) and
``--json``; those that write take ``--token`` (default ``$LABD_TOKEN``). Errors from
the server are printed as it words them, and the exit status is 2; 1 means a trial
that was waited for did not succeed (or, for a rerun, did not reproduce).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx

from labd.errors import LabError
from labd.sim import registry
from labd.sim.params import parse_assignments
from repository.errors import ArchiveError
from repository.export import export

DEFAULT_SERVER = "http://127.0.0.1:8080"
ENDED = ("succeeded", "failed", "cancelled")


class CommandError(Exception):
    """What went wrong, as the person at the terminal should read it."""


class Client:
    """A small client of the lab's HTTP API."""

    def __init__(self, server: str, token: str | None = None, timeout: float = 330.0) -> None:
        self.server = server.rstrip("/")
        headers = {"Authorization": f"Bearer {token}"} if token else {}
        # Submitting fetches the repository first: allow for the lab's fetch time limit.
        self.http = httpx.Client(base_url=self.server, headers=headers, timeout=timeout)

    def close(self) -> None:
        self.http.close()

    def request(self, method: str, path: str, **kwargs: Any) -> Any:
        try:
            response = self.http.request(method, path, **kwargs)
        except httpx.HTTPError as err:
            raise CommandError(f"cannot reach the lab at {self.server}: {err}") from None
        if response.status_code >= 400:
            raise CommandError(f"{_error_text(response)} (HTTP {response.status_code})")
        return response.json()

    def download(self, path: str, dest: Path) -> int:
        partial = dest.with_name(dest.name + ".partial")
        try:
            with self.http.stream("GET", path) as response:
                if response.status_code >= 400:
                    response.read()
                    raise CommandError(f"{_error_text(response)} (HTTP {response.status_code})")
                size = 0
                with partial.open("wb") as out:
                    for chunk in response.iter_bytes():
                        out.write(chunk)
                        size += len(chunk)
        except httpx.HTTPError as err:
            partial.unlink(missing_ok=True)
            raise CommandError(f"the download from {self.server} broke off: {err}") from None
        partial.rename(dest)
        return size

    def wait(self, trial_ids: list[int], poll: float = 1.0) -> list[dict[str, Any]]:
        """Wait until every trial has ended; print each as it ends (to stderr)."""
        pending = set(trial_ids)
        rows: dict[int, dict[str, Any]] = {}
        while pending:
            for trial_id in sorted(pending):
                row = self.request("GET", f"/api/trials/{trial_id}")
                if row["status"] in ENDED:
                    rows[trial_id] = row
                    pending.discard(trial_id)
            if pending:
                time.sleep(poll)
        return [rows[t] for t in trial_ids]


def add_parsers(commands: Any) -> None:
    def common(parser: argparse.ArgumentParser, *, write: bool = False) -> None:
        parser.add_argument(
            "--server",
            default=os.environ.get("LABD_SERVER", DEFAULT_SERVER),
            help="the lab's HTTP API (default $LABD_SERVER or %(default)s)",
        )
        parser.add_argument("--json", action="store_true", help="print JSON for scripts")
        if write:
            parser.add_argument(
                "--token",
                default=os.environ.get("LABD_TOKEN"),
                help="your token (default $LABD_TOKEN; `labd users add NAME` makes one)",
            )

    p = commands.add_parser("submit", help="queue a trial of a repository at a ref")
    p.add_argument("repository", metavar="REPO_URL", help="a git URL (or a local repository)")
    p.add_argument("--ref", help="branch, tag or commit (default: the repository's HEAD)")
    p.add_argument("--task", required=True, help="the task (labd tasks lists them)")
    p.add_argument("--seed", type=int, default=0, help="the episode's seed (default 0)")
    p.add_argument("--param", action="append", default=[], metavar="NAME=VALUE")
    p.add_argument("--wait", action="store_true", help="wait for the trial to end")
    common(p, write=True)

    p = commands.add_parser("trials", help="list trials in the archive, newest first")
    p.add_argument("--repo", help="repository URL")
    p.add_argument("--commit", help="a commit or its first digits")
    p.add_argument("--task")
    p.add_argument("--status", choices=["queued", "running", *ENDED])
    p.add_argument("--user", help="the submitter")
    p.add_argument("--limit", type=int, default=20)
    p.add_argument("--before", type=int, help="the next page: the cursor a page printed")
    common(p)

    p = commands.add_parser("show", help="one trial: what ran, how it ended, its record")
    p.add_argument("trial", type=int, metavar="TRIAL")
    common(p)

    p = commands.add_parser("download", help="download a trial's MCAP record")
    p.add_argument("trial", type=int, metavar="TRIAL")
    p.add_argument("-o", "--output", type=Path, help="file (default trial-N.mcap)")
    common(p)

    p = commands.add_parser("rerun", help="rerun a trial, or a commit's trials, to check them")
    p.add_argument("target", metavar="COMMIT|TRIAL", help="a trial number or a commit")
    p.add_argument("--all", action="store_true", help="every trial of the commit, not the newest")
    p.add_argument("--wait", action="store_true", help="wait and print the verdicts")
    common(p, write=True)

    p = commands.add_parser("cancel", help="cancel a queued or running trial")
    p.add_argument("trial", type=int, metavar="TRIAL")
    common(p, write=True)

    p = commands.add_parser("export", help="export a trial as observation-action pairs")
    p.add_argument("trial", type=int, metavar="TRIAL")
    p.add_argument("--format", required=True, choices=["lerobot", "parquet"])
    p.add_argument("-o", "--output", type=Path, help="folder (default trial-N-FORMAT)")
    common(p)


COMMANDS = ("submit", "trials", "show", "download", "rerun", "cancel", "export")


def main(args: argparse.Namespace) -> int:
    client = Client(args.server, getattr(args, "token", None))
    try:
        handler = globals()[f"_{args.command}"]
        code: int = handler(client, args)
        return code
    except (CommandError, LabError, ArchiveError) as err:
        print(f"labd {args.command}: {err}", file=sys.stderr)
        return 2
    finally:
        client.close()


def _submit(client: Client, args: argparse.Namespace) -> int:
    body = {
        "repository": args.repository,
        "ref": args.ref,
        "task": args.task,
        "seed": args.seed,
        "params": parse_assignments(args.param),
    }
    row = client.request("POST", "/api/trials", json=body)
    if not args.wait:
        _print(args, row, lambda: _queued_lines(row))
        return 0
    if not args.json:
        print("\n".join(_queued_lines(row)), flush=True)
    [row] = client.wait([row["id"]])
    _print(args, row, lambda: _trial_lines(row))
    return 0 if row["status"] == "succeeded" else 1


def _trials(client: Client, args: argparse.Namespace) -> int:
    query = {
        "repository": args.repo,
        "commit": args.commit,
        "task": args.task,
        "status": args.status,
        "user": args.user,
        "limit": args.limit,
        "before": args.before,
    }
    page = client.request(
        "GET", "/api/trials", params={k: v for k, v in query.items() if v is not None}
    )
    _print(args, page, lambda: _table(page))
    return 0


def _show(client: Client, args: argparse.Namespace) -> int:
    row = client.request("GET", f"/api/trials/{args.trial}")
    _print(args, row, lambda: _trial_lines(row, full=True))
    return 0


def _download(client: Client, args: argparse.Namespace) -> int:
    dest = args.output or Path(f"trial-{args.trial}.mcap")
    size = client.download(f"/api/trials/{args.trial}/data.mcap", dest)
    _print(args, {"path": str(dest), "size": size}, lambda: [f"{dest} ({size:,} bytes)"])
    return 0


def _rerun(client: Client, args: argparse.Namespace) -> int:
    target = args.target
    if target.isdigit() and len(target) < 7:
        originals = [int(target)]
    else:
        page = client.request("GET", f"/api/commits/{target}")
        originals = [t["id"] for t in page["trials"]]
        if not originals:
            raise CommandError(f"commit {target} has no trials to rerun")
        originals = originals if args.all else originals[:1]
    made = [client.request("POST", f"/api/trials/{t}/rerun") for t in originals]
    if not args.wait:
        _print(args, made, lambda: [line for row in made for line in _queued_lines(row)])
        return 0
    if not args.json:
        for row in made:
            print(f"trial {row['id']} queued: a rerun of trial {row['rerun_of']}", flush=True)
    done = client.wait([row["id"] for row in made])
    _print(args, done, lambda: [_verdict_line(row) for row in done])
    return 0 if all(row["reproduced"] for row in done) else 1


def _cancel(client: Client, args: argparse.Namespace) -> int:
    row = client.request("POST", f"/api/trials/{args.trial}/cancel")
    word = "cancelled" if row["status"] == "cancelled" else f"{row['status']}"
    _print(args, row, lambda: [f"trial {row['id']}: {word}: {row['reason']}"])
    return 0


def _export(client: Client, args: argparse.Namespace) -> int:
    row = client.request("GET", f"/api/trials/{args.trial}")
    if not row["mcap"]:
        raise CommandError(f"trial {args.trial} has no record to export ({row['status']})")
    observations, actions = registry.get(row["task"]).topics()
    out = args.output or Path(f"trial-{args.trial}-{args.format}")
    with tempfile.TemporaryDirectory(prefix="labd-export-") as folder:
        mcap = Path(folder) / "trial.mcap"
        client.download(f"/api/trials/{args.trial}/data.mcap", mcap)
        summary = export(
            mcap,
            out,
            args.format,
            observations=observations,
            actions=actions,
            provenance={
                "trial": row["id"],
                "url": row["url"],
                "repository": row["repository"],
                "commit": row["commit"],
                "task": row["task"],
                "manifest_digest": row["manifest_digest"],
                "data_digest": row["data_digest"],
                "manifest": row["manifest"],
            },
        )
    info = {"path": str(out), "format": args.format, "frames": summary.frames}
    _print(args, info, lambda: [f"{out}: {summary.frames} frames ({args.format})"])
    return 0


# -- printing ----------------------------------------------------------------------------


def _print(args: argparse.Namespace, data: Any, lines: Any) -> None:
    if args.json:
        print(json.dumps(data, indent=2))
    else:
        for line in lines():
            print(line)


def _queued_lines(row: dict[str, Any]) -> Iterator[str]:
    ref = f" ({row['ref']})" if row["ref"] and row["ref"] != row["commit"] else ""
    what = f"a rerun of trial {row['rerun_of']}" if row["rerun_of"] else row["task"]
    yield f"trial {row['id']} queued: {what}"
    yield f"  {row['repository']} @ {row['commit']}{ref}"
    yield f"  seed {row['seed']}" + (f", params {_params(row['params'])}" if row["params"] else "")
    yield f"  follow it: labd show {row['id']}   ({row['url']})"


def _trial_lines(row: dict[str, Any], full: bool = False) -> Iterator[str]:
    yield f"trial {row['id']}: {row['status']}: {row['reason']}"
    ref = f" ({row['ref']})" if row["ref"] and row["ref"] != row["commit"] else ""
    yield f"  repository {row['repository']}"
    yield f"  commit     {row['commit']}{ref}"
    params = f", params {_params(row['params'])}" if row["params"] else ""
    yield f"  task       {row['task']}, seed {row['seed']}{params}"
    yield f"  submitter  {row['submitter']}, submitted {row['created']}"
    if row["rerun_of"]:
        yield f"  rerun of   trial {row['rerun_of']}: {row['verdict'] or 'not compared yet'}"
    if row["metrics"]:
        yield "  metrics    " + ", ".join(f"{k}={_fmt(v)}" for k, v in row["metrics"].items())
    if row["manifest_digest"]:
        yield f"  manifest   sha256:{row['manifest_digest']}"
    if row["data_digest"]:
        yield f"  data       sha256:{row['data_digest']}"
    if row["mcap"]:
        yield f"  record     {row['mcap']['url']} ({row['mcap']['size']:,} bytes)"
    for stream, url in row["logs"].items():
        yield f"  {stream:<10} {url}"
    if full and row.get("manifest"):
        versions = row["manifest"].get("versions", {})
        yield "  versions   " + ", ".join(f"{k} {v}" for k, v in versions.items())


def _verdict_line(row: dict[str, Any]) -> str:
    if row["status"] != "succeeded" and not row["verdict"]:
        return f"trial {row['id']} (rerun of {row['rerun_of']}): {row['status']}: {row['reason']}"
    return f"trial {row['id']} (rerun of {row['rerun_of']}): {row['verdict']}"


def _table(page: dict[str, Any]) -> Iterator[str]:
    rows = page["trials"]
    if not rows:
        yield "no trials"
        return
    yield (
        f"{'ID':>6}  {'STATUS':<9}  {'TASK':<12}  {'COMMIT':<12}  {'SEED':>5}  "
        f"{'USER':<10}  REPOSITORY"
    )
    for r in rows:
        yield (
            f"{r['id']:>6}  {r['status']:<9}  {r['task']:<12}  {r['commit'][:12]:<12}  "
            f"{r['seed']:>5}  {r['submitter'][:10]:<10}  {r['repository']}"
            + (f"  (rerun of {r['rerun_of']}: {r['verdict'] or '...'})" if r["rerun_of"] else "")
        )
    if page["next"]:
        yield f"more: --before {page['next']}"


def _params(params: dict[str, Any]) -> str:
    return " ".join(f"{k}={v}" for k, v in params.items())


def _fmt(value: Any) -> str:
    return f"{value:.4g}" if isinstance(value, float) else str(value)


def _error_text(response: httpx.Response) -> str:
    try:
        return str(response.json().get("error") or response.text)
    except ValueError:
        return response.text.strip() or response.reason_phrase
