"""``labd match``: two repositories play a task teams play; the matches; a task's ladder.

    labd match REPO_A REPO_B --task soccer-1v1 [--ref-a REF] [--ref-b REF] [--seeds N]
               [--param NAME=VALUE ...] [--wait] [--json]
    labd matches [--task T] [--repository R] [--commit SHA] [--user U] [--limit N]
                 [--before ID] [--json]
    labd ladder TASK [--json]
    labd ladder join REPO --task TASK [--ref REF] [--json]

``match`` queues a match (``POST /api/matches``): each seed played twice, A at home then
B at home. With ``--wait`` it prints a line on stderr whenever the match moves, until
every leg has ended and every leg with a result has its replay's verdict (at most
``REPLAYS`` seconds more, as ``labd evaluate --wait``), then each leg's result and the
score. Its exit code (``labd.commands.common``): 0 the match finished, every leg with a
result; 4 it was cancelled; 3 a leg ended without a result (it broke: every side
forfeited, or the lab failed), so the score is not the teams' whole; 2 the lab refused
it (an unknown task, one not played by two teams, a repository that does not resolve).
Without ``--wait`` it exits 0 once the match is queued.

The API's bodies are read with the models below, which mirror ``labd.api.matches``'s
(that module imports FastAPI, which a client command must not load);
tests/labd/test_cli_matches.py holds the two to each other.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable, Iterator
from typing import Any

from pydantic import BaseModel, Field

from labd.commands.common import (
    REPOSITORY_HELP,
    ExitCode,
    emit,
    fail,
    param_option,
    repository_arg,
    server_options,
)
from repository.errors import ArchiveError
from repository.match import (
    MAX_SEEDS,
    MAX_STEP_DEADLINE,
    STEP_DEADLINE,
    LadderRow,
    LegRow,
    Match,
    Team,
    other,
)
from repository.trial import Status, TeamRef
from scheduler.client import ApiClient
from scheduler.errors import RemoteError

POLL = 2.0  # seconds between looks at a running match
REPLAYS = 120.0  # seconds to wait, after the last leg, for the replays' verdicts
VERIFYING = " to verify them"
CODES = """exit codes: 0 the match finished (without --wait: it was queued); 2 the lab
refused it (an unknown task, one not played by two teams, a repository that does not
resolve) or could not be reached; 3 a leg ended without a result (every side forfeited,
or the lab broke it): the score is not the teams' whole; 4 the match was cancelled"""


class MatchView(Match):
    """A match, with where to find it (``labd.api.matches.MatchView``)."""

    url: str = Field(description="this match in the API")
    page: str = Field(description="its web page")


class MatchPage(BaseModel):
    """A page of ``GET /api/matches`` (``labd.api.matches.MatchPage``)."""

    matches: list[MatchView]
    next: int | None = Field(description="`before` for the next page; null on the last")


class Ladder(BaseModel):
    """``GET /api/ladders/{task}`` (``labd.api.matches.Ladder``): best first."""

    task: str
    rows: list[LadderRow]


def add_parser(commands: Any) -> None:
    p = commands.add_parser(
        "match",
        description="Queue a match: each seed played twice, A at home then B at home.",
        epilog=CODES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("repository_a", metavar="REPO_A", type=repository_arg, help=REPOSITORY_HELP)
    p.add_argument("repository_b", metavar="REPO_B", type=repository_arg, help=REPOSITORY_HELP)
    p.add_argument(
        "--task", required=True, help="a task teams play (soccer-1v1; `labd tasks` lists them)"
    )
    p.add_argument(
        "--ref-a", metavar="REF", help="A's branch, tag or commit (default: its repository's HEAD)"
    )
    p.add_argument(
        "--ref-b", metavar="REF", help="B's branch, tag or commit (default: its repository's HEAD)"
    )
    p.add_argument(
        "--seeds",
        type=seeds,
        default=2,
        metavar="N",
        help=f"play seeds 0 to N-1, two legs each, 1 to {MAX_SEEDS} (default: %(default)s)",
    )
    param_option(p)
    p.add_argument(
        "--step-deadline",
        type=float,
        default=STEP_DEADLINE,
        metavar="SECONDS",
        help="a team that keeps the other waiting longer for its step forfeits the leg"
        f" (1 to {MAX_STEP_DEADLINE:g}; default: %(default)g)",
    )
    p.add_argument(
        "--wait",
        action="store_true",
        help="wait for every leg and its replay's verdict, printing progress on stderr,"
        " then the result (default: no)",
    )
    server_options(p, write=True)

    p = commands.add_parser("matches")
    p.add_argument("--task", help="only this task's (default: all)")
    p.add_argument(
        "--repository",
        type=repository_arg,
        help="only those this repository URL or folder played, as A or B (default: all)",
    )
    p.add_argument("--commit", help="only those this commit played, or its first 4+ digits")
    p.add_argument("--user", help="only this submitter's (default: everyone's)")
    p.add_argument("--limit", type=int, default=20, help="matches per page (default: %(default)s)")
    p.add_argument("--before", type=int, help="the next page: the cursor a page printed")
    server_options(p)

    p = commands.add_parser(
        "ladder",
        usage="labd ladder TASK [--json]\n"
        "       labd ladder join REPO --task TASK [--ref REF] [--json]",
        description="A task's ladder; or, with join, enter a commit on it: the lab queues its"
        " matches against commits entered before (those with the fewest matches and those"
        " rated nearest it, in turn, three at most).",
    )
    p.add_argument("words", nargs="+", metavar="TASK | join REPO", help="what to do")
    p.add_argument("--task", help="join: the ladder's task (soccer-1v1)")
    p.add_argument("--ref", help="join: the branch, tag or commit (default: its repository's HEAD)")
    server_options(p, write=True)


def seeds(text: str) -> int:
    """An argparse type: how many seeds a match plays, 1 to ``MAX_SEEDS``."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number of seeds") from None
    if not 1 <= value <= MAX_SEEDS:
        raise argparse.ArgumentTypeError(f"{value}: a match plays 1 to {MAX_SEEDS} seeds")
    return value


def main(args: argparse.Namespace) -> int:
    try:
        with ApiClient(args.server, getattr(args, "token", None)) as client:
            return int(COMMANDS[args.command](client, args))
    except (RemoteError, ArchiveError) as err:
        return fail(args, str(err))


def _match(client: ApiClient, args: argparse.Namespace) -> int:
    body = {
        "task": args.task,
        "a": {"repository": args.repository_a, "ref": args.ref_a},
        "b": {"repository": args.repository_b, "ref": args.ref_b},
        "seeds": args.seeds,
        "step_deadline": args.step_deadline,
        "params": dict(args.param),
    }
    match = client.post("/api/matches", MatchView, json=body)
    queued = [queued_line(match), f"  follow it: {match.page}"]
    if not args.wait:
        emit(args, match.model_dump(mode="json"), lambda: queued)
        return ExitCode.SUCCESS
    _stderr(queued[0])
    match = follow(client, match, _stderr)
    emit(args, match.model_dump(mode="json"), lambda: result_lines(match))
    code, said = verdict(match)
    if said is not None:
        _stderr(said)
    return code


def follow(client: ApiClient, match: MatchView, progress: Callable[[str], None]) -> MatchView:
    """Poll until every leg has ended and every leg with a result has its replay's
    verdict (a worker replays a record after filing it; at most ``REPLAYS`` seconds
    more), telling ``progress`` a line whenever the match moves."""
    said = ""
    ended: float | None = None
    while True:
        if match.status.ended:
            ended = ended or time.monotonic()
        last = ended is not None and (not replaying(match) or time.monotonic() - ended > REPLAYS)
        line = progress_line(match)
        if line != said and not (last and said.endswith(VERIFYING)):
            progress(line)
            said = line
        if last:
            return match
        time.sleep(POLL)
        match = client.get(f"/api/matches/{match.id}", MatchView)


def replaying(match: Match) -> int:
    """Legs with a result whose replay has no verdict yet."""
    return sum(leg.counts and leg.verified is None for leg in match.legs)


def verdict(match: Match) -> tuple[ExitCode, str | None]:
    """The exit code of a match followed to its end, and the line on stderr that says
    why it is not 0 (None when it is)."""
    if match.status is Status.CANCELLED:
        unplayed = sum(leg.status is Status.CANCELLED for leg in match.legs)
        return ExitCode.CANCELLED, f"match {match.id} was cancelled ({_legs(unplayed)} unplayed)"
    broken = [leg for leg in match.legs if leg.status is Status.FINISHED and not leg.counts]
    if broken:
        which = ", ".join(str(leg.leg) for leg in broken)
        return ExitCode.ERROR, (
            f"match {match.id}: {_legs(len(broken))} ended without a result (leg {which}):"
            " the score counts only the others"
        )
    return ExitCode.SUCCESS, None


# -- printing ----------------------------------------------------------------------------


def queued_line(match: Match) -> str:
    """``match 7 queued: A (commit) against B (commit), 4 legs``."""
    return (
        f"match {match.id} queued: {_team(match.a)} against {_team(match.b)},"
        f" {_legs(len(match.legs))}"
    )


def progress_line(match: Match) -> str:
    """Where a match is, in a line: its legs, and the score so far."""
    left = replaying(match)
    if match.status.ended and left:
        return f"match {match.id}: {match.status}; replaying {_legs(left)}{VERIFYING}"
    done = sum(leg.status.ended for leg in match.legs)
    running = sum(leg.status is Status.RUNNING for leg in match.legs)
    queued = sum(leg.status is Status.QUEUED for leg in match.legs)
    return (
        f"match {match.id}: {done}/{len(match.legs)} legs done, {running} running,"
        f" {queued} queued; {_score(match)}"
    )


def result_lines(match: MatchView) -> Iterator[str]:
    yield f"match {match.id}: {match.task} (version {match.task_version}), {match.status}"
    yield f"  A  {_team(match.a, full=True)}"
    yield f"  B  {_team(match.b, full=True)}"
    if match.params:
        yield "  params " + " ".join(f"{k}={v}" for k, v in match.params.items())
    for leg in match.legs:
        yield f"  {leg_line(leg)}"
    yield f"  score: {_score(match)}"
    unverified = [leg for leg in match.legs if leg.counts and leg.verified is not True]
    if match.verified:
        yield "  verified: the lab's replay of every leg with a result reproduced its record"
    elif match.status.ended and unverified:
        yield f"  not verified: {_legs(len(unverified))} without a verified replay"
    if match.signature:
        yield f"  signed by the lab ({match.signature.get('key')})"
    yield f"  {match.page}"


def leg_line(leg: LegRow) -> str:
    """``leg 0, seed 0, A at home: A won 1-0 (goal)``: the winner's goals first."""
    where = f"leg {leg.leg}, seed {leg.seed}, {leg.home.upper()} at home"
    if leg.result is None:  # not played (yet), or broken: its status and reason
        state = f"no result ({leg.outcome})" if leg.status is Status.FINISHED else leg.status
        return f"{where}: {state}" + (f": {leg.said}" if leg.said else "")
    goals = leg.goals or {}
    first: Team = "a" if leg.result == "draw" else leg.result
    tally = f"{goals.get(first, 0)}-{goals.get(other(first), 0)}"
    what = f"a draw {tally}" if leg.result == "draw" else f"{first.upper()} won {tally}"
    how = str(leg.reason or "?")
    if leg.forfeited:
        how += " by " + " and ".join(team.upper() for team in leg.forfeited)
    replay = {True: "", False: "; its replay did not reproduce it", None: "; not replayed yet"}
    return f"{where}: {what} ({how}){replay[leg.verified]}"


def _matches(client: ApiClient, args: argparse.Namespace) -> int:
    query = {
        "task": args.task,
        "repository": args.repository,
        "commit": args.commit,
        "submitter": args.user,
        "limit": args.limit,
        "before": args.before,
    }
    params = {k: v for k, v in query.items() if v is not None}
    page = client.get("/api/matches", MatchPage, params=params)
    emit(args, page.model_dump(mode="json"), lambda: matches_table(page))
    return ExitCode.SUCCESS


def matches_table(page: MatchPage) -> Iterator[str]:
    if not page.matches:
        yield "no matches"
        return
    a = [_team(m.a) for m in page.matches]
    b = [_team(m.b) for m in page.matches]
    wa, wb = max(len("A"), *map(len, a)), max(len("B"), *map(len, b))
    yield (
        f"{'ID':>6}  {'TASK':<12}  {'A':<{wa}}  {'B':<{wb}}  {'A-B-DRAWN':<9}  {'STATUS':<9}  "
        "VERIFIED"
    )
    for m, team_a, team_b in zip(page.matches, a, b, strict=True):
        s = m.score
        score = f"{s.a}-{s.b}-{s.draws}"
        checked = "yes" if m.verified else "no"
        yield (
            f"{m.id:>6}  {m.task:<12}  {team_a:<{wa}}  {team_b:<{wb}}  {score:<9}  "
            f"{m.status:<9}  {checked}"
        )
    if page.next:
        yield f"more: --before {page.next}"


class Joined(BaseModel):
    """``POST /api/ladders/{task}/entries`` (``labd.api.matches.JoinedView``)."""

    entry: int
    matches: list[MatchView]


def _ladder(client: ApiClient, args: argparse.Namespace) -> int:
    words = args.words
    if words[0] == "join":
        if len(words) != 2 or not args.task:
            return fail(args, "labd ladder join REPO --task TASK: one repository, and the task")
        return _join(client, args, repository_arg(words[1]))
    if len(words) != 1 or args.task or args.ref:
        return fail(
            args, "labd ladder TASK shows a ladder; labd ladder join REPO --task TASK enters one"
        )
    ladder = client.get(f"/api/ladders/{words[0]}", Ladder)
    emit(args, ladder.model_dump(mode="json"), lambda: ladder_table(ladder))
    return ExitCode.SUCCESS


def _join(client: ApiClient, args: argparse.Namespace, repository: str) -> int:
    body = {"repository": repository, "ref": args.ref}
    joined = client.post(f"/api/ladders/{args.task}/entries", Joined, json=body)

    def lines() -> Iterator[str]:
        if not joined.matches:
            yield (
                f"entered on the {args.task} ladder (entry {joined.entry}): the first one;"
                " its matches come as others join"
            )
            return
        me = joined.matches[0].a
        yield (
            f"{_team(me)} entered on the {args.task} ladder (entry {joined.entry}):"
            f" {len(joined.matches)} match{'' if len(joined.matches) == 1 else 'es'} queued"
        )
        for m in joined.matches:
            yield f"  match {m.id} against {_team(m.b)}: {m.page}"

    emit(args, joined.model_dump(mode="json"), lines)
    return ExitCode.SUCCESS


def ladder_table(ladder: Ladder) -> Iterator[str]:
    if not ladder.rows:
        yield (
            f"{ladder.task}: no commit rated yet (a match counts once it has finished and"
            " every leg with a result verified)"
        )
        return
    width = max(len("REPOSITORY"), *(len(r.repository) for r in ladder.rows))
    yield (
        f"{'RANK':>4}  {'REPOSITORY':<{width}}  {'COMMIT':<12}  {'RATING':>6}  "
        f"{'95 % INTERVAL':<13}  {'MATCHES':>7}  W-L-D"
    )
    for rank, r in enumerate(ladder.rows, 1):
        low, high = r.interval
        interval = f"{low:.0f} to {high:.0f}"
        yield (
            f"{rank:>4}  {r.repository:<{width}}  {r.commit[:12]:<12}  {r.rating:>6.0f}  "
            f"{interval:<13}  {r.matches:>7}  {r.wins}-{r.losses}-{r.draws}"
        )


def _team(team: TeamRef, full: bool = False) -> str:
    if not full:
        return f"{team.repository} ({team.commit[:12]})"
    ref = f" ({team.ref})" if team.ref and team.ref != team.commit else ""
    return f"{team.repository} @ {team.commit}{ref}"


def _score(match: Match) -> str:
    s = match.score
    return f"A {s.a}, B {s.b}, {s.draws} drawn"


def _legs(n: int) -> str:
    return f"{n} leg" if n == 1 else f"{n} legs"


def _stderr(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


COMMANDS: dict[str, Callable[[ApiClient, argparse.Namespace], int]] = {
    "match": _match,
    "matches": _matches,
    "ladder": _ladder,
}
