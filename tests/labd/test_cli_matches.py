"""``labd match``, ``labd matches`` and ``labd ladder`` run in process (``labd.cli.main``)
against a real lab on 127.0.0.1 (its HTTP API, no workers): each leg is claimed and
filed here as a worker files it, its result in its metrics as the leg runner writes
them, so every ending a command must report is made on purpose. A command that waits
runs on a thread; its progress lines are handed to the test as they are printed, so
each step is taken once the command has seen the one before."""

from __future__ import annotations

import json
import os
import queue
import sys
from collections.abc import Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from contextlib import contextmanager
from typing import Any

import pytest

from labd.api import matches as api
from labd.cli import main
from labd.commands import match as command
from labd.commands.common import ExitCode
from labd.sim import registry
from repository.trial import Claim, Filing
from scheduler.client import ApiClient
from scheduler.fetch import FetchPolicy
from tests.fakes import verify_episodes
from tests.helpers.githttp import GitRepo
from tests.helpers.labs import lab_config, running
from tests.labd.test_cli_imports import LAB, loaded

TASK = "soccer-1v1"
WAIT = 60.0  # seconds a test waits for what the command or the lab does
POLL = 0.02  # seconds between the waiting command's looks at the match, here


def team_toml(task: str = TASK) -> str:
    return f'[controller]\ncommand = ["python", "c.py"]\ntask = "{task}"\n'


@pytest.fixture
def server(tmp_path, monkeypatch) -> Iterator[Any]:
    """A lab without workers that takes local repositories; the commands find it (and
    alice's token) in the environment, as a user's shell gives them."""
    fetch = FetchPolicy(schemes=frozenset({"file"}))
    with running(lab_config(tmp_path / "data", robots=(), service={"fetch": fetch})) as server:
        service = server.lab.service
        service.queue.check = None  # the filings here name no record file
        monkeypatch.setenv("LABD_SERVER", server.http_url())
        monkeypatch.setenv("LABD_TOKEN", service.index.add_user("alice", max_daily=500))
        monkeypatch.setattr(command, "POLL", POLL)
        yield server


@pytest.fixture
def teams(tmp_path) -> dict[str, GitRepo]:
    """Three tiny teams, ``a``, ``b`` and ``c``, each its own repository."""
    return {
        name: GitRepo.create(
            tmp_path / f"team-{name}", {"lab.toml": team_toml(), "c.py": f"# {name}\n"}
        )
        for name in "abc"
    }


@pytest.fixture
def said(monkeypatch) -> queue.Queue[str]:
    """The lines the match command prints on stderr, as it prints them."""
    lines: queue.Queue[str] = queue.Queue()

    def stderr(line: str) -> None:
        print(line, file=sys.stderr, flush=True)
        lines.put(line)

    monkeypatch.setattr(command, "_stderr", stderr)
    return lines


def run(capsys, *argv: str) -> tuple[int, str, str]:
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def next_line(lines: queue.Queue[str]) -> str:
    return lines.get(timeout=WAIT)


def claim(service: Any) -> Claim:
    """The next queued leg, claimed as a worker claims it."""
    claimed = service.queue.claim("w")
    assert claimed is not None, "no leg is queued"
    return claimed


def file_leg(
    service: Any,
    leg: Claim,
    winner: str,
    ended_by: str,
    goals: tuple[int, int] = (0, 0),
    forfeited: str = "",
    *,
    verified: bool = True,
) -> None:
    """File ``leg`` as a worker files a leg it played: its result from the sides' view
    (``winner`` home, away or draw; "" with no result, an error), its replay verified
    beforehand unless told otherwise."""
    if verified:
        verify_episodes(service, [leg.id])
    metrics = {
        "winner": winner,
        "ended_by": ended_by,
        "forfeited": forfeited,
        "home_goals": goals[0],
        "away_goals": goals[1],
        "steps": 40,
    }
    filing = Filing(
        status="finished",
        outcome="success" if winner else "error",
        reason=f"{winner} won at tick 40" if winner else "no result, every side forfeited",
        data_digest=f"{leg.id:064x}",
        metrics=metrics,
    )
    assert service.queue.finish(leg.id, "w", filing)


def play(service: Any, *results: tuple[Any, ...]) -> None:
    """Claim and file the next legs, one result each (``file_leg``'s arguments)."""
    for result in results:
        file_leg(service, claim(service), *result)


@contextmanager
def in_background(*argv: str) -> Iterator[Future[int]]:
    """Run a command on a thread. A test that fails while the command still follows
    its match does not wait for it: the thread ends when the lab under it stops."""
    pool = ThreadPoolExecutor(1)
    try:
        yield pool.submit(main, list(argv))
    finally:
        pool.shutdown(wait=False)


def short(repo: GitRepo) -> str:
    return f"{repo.path.resolve()} ({repo.git('rev-parse', 'HEAD').strip()[:12]})"


def test_a_match_waited_for_says_each_step_then_each_leg_and_exits_0(
    server, teams, said, capsys, tmp_path, monkeypatch
):
    """``labd match A B --wait`` (relative paths, made absolute) says the match is
    queued, then a line each time it moves, waits for the last leg's replay verdict,
    prints one line per leg (who was at home, who won, the winner's goals first, how)
    and the score, and exits 0."""
    service = server.lab.service
    monkeypatch.chdir(tmp_path)
    a, b = teams["a"], teams["b"]
    with in_background("match", "team-a", "team-b", "--task", TASK, "--wait") as done:
        queued = f"match 1 queued: {short(a)} against {short(b)}, 4 legs"
        assert next_line(said) == queued
        steps = [next_line(said)]
        results: list[tuple[Any, ...]] = [
            ("home", "goal", (1, 0)),  # leg 0, A at home
            ("draw", "time"),  # leg 1, B at home
            ("home", "forfeit", (0, 0), "away"),  # leg 2, A at home; B forfeits
        ]
        for result in results:
            leg = claim(service)
            steps.append(next_line(said))
            file_leg(service, leg, *result)
            steps.append(next_line(said))
        last = claim(service)
        steps.append(next_line(said))
        file_leg(service, last, "home", "goal", (2, 1), verified=False)  # leg 3, B at home
        steps.append(next_line(said))
        verify_episodes(service, [last.id])
        code = done.result(WAIT)
    out, err = capsys.readouterr()
    assert code == ExitCode.SUCCESS, out + err
    assert steps == [
        "match 1: 0/4 legs done, 0 running, 4 queued; A 0, B 0, 0 drawn",
        "match 1: 0/4 legs done, 1 running, 3 queued; A 0, B 0, 0 drawn",
        "match 1: 1/4 legs done, 0 running, 3 queued; A 1, B 0, 0 drawn",
        "match 1: 1/4 legs done, 1 running, 2 queued; A 1, B 0, 0 drawn",
        "match 1: 2/4 legs done, 0 running, 2 queued; A 1, B 0, 1 drawn",
        "match 1: 2/4 legs done, 1 running, 1 queued; A 1, B 0, 1 drawn",
        "match 1: 3/4 legs done, 0 running, 1 queued; A 2, B 0, 1 drawn",
        "match 1: 3/4 legs done, 1 running, 0 queued; A 2, B 0, 1 drawn",
        "match 1: finished; replaying 1 leg to verify them",
    ]
    assert said.empty(), "nothing more on stderr once the match has ended"
    lines = out.splitlines()
    assert lines[0] == f"match 1: {TASK} (version {registry.get(TASK).version}), finished"
    assert lines[1:3] == [
        f"  A  {a.path.resolve()} @ {a.git('rev-parse', 'HEAD').strip()}",
        f"  B  {b.path.resolve()} @ {b.git('rev-parse', 'HEAD').strip()}",
    ]
    assert lines[3:9] == [
        "  leg 0, seed 0, A at home: A won 1-0 (goal)",
        "  leg 1, seed 0, B at home: a draw 0-0 (time)",
        "  leg 2, seed 1, A at home: A won 0-0 (forfeit by B)",
        "  leg 3, seed 1, B at home: B won 2-1 (goal)",
        "  score: A 2, B 1, 1 drawn",
        "  verified: the lab's replay of every leg with a result reproduced its record",
    ]
    assert lines[-1].endswith("/matches/1")


def test_json_without_wait_is_the_queued_match(server, teams, capsys):
    """``labd match --json`` prints the match the lab queued, as the API gives it, and
    exits 0 at once: each seed twice, A at home first, the parameters as asked."""
    a, b = teams["a"], teams["b"]
    code, out, err = run(
        capsys, "match", str(a.path), str(b.path), "--task", TASK, "--seeds", "1",
        "--param", "time_limit=20", "--json",
    )  # fmt: skip
    assert code == ExitCode.SUCCESS, err
    shown = json.loads(out)
    with ApiClient(server.http_url()) as client:
        assert shown == client.get("/api/matches/1", command.MatchView).model_dump(mode="json")
    assert shown["status"] == "queued"
    assert [(leg["seed"], leg["home"]) for leg in shown["legs"]] == [(0, "a"), (0, "b")]
    assert shown["params"]["time_limit"] == 20
    assert shown["a"]["repository"] == str(a.path.resolve())


def test_a_cancelled_match_exits_4_with_its_json(server, teams, said, capsys):
    """A match cancelled while ``labd match --wait --json`` follows it: the command
    prints the cancelled match as JSON, says why on stderr, and exits 4 (cancelled)."""
    service = server.lab.service
    a, b = (str(teams[n].path) for n in "ab")
    with in_background("match", a, b, "--task", TASK, "--seeds", "1", "--wait", "--json") as done:
        assert next_line(said).startswith("match 1 queued: ")
        next_line(said)
        leg = claim(service)  # the command may see the leg running before it is filed
        assert next_line(said) == "match 1: 0/2 legs done, 1 running, 1 queued; A 0, B 0, 0 drawn"
        file_leg(service, leg, "home", "goal", (1, 0))
        assert next_line(said) == "match 1: 1/2 legs done, 0 running, 1 queued; A 1, B 0, 0 drawn"
        with ApiClient(server.http_url(), os.environ["LABD_TOKEN"]) as alice:
            alice.post("/api/matches/1/cancel", command.MatchView)
        code = done.result(WAIT)
    out, err = capsys.readouterr()
    assert code == ExitCode.CANCELLED, out + err
    shown = json.loads(out)
    assert shown["status"] == "cancelled"
    assert [leg["status"] for leg in shown["legs"]] == ["finished", "cancelled"]
    assert shown["score"] == {"a": 1, "b": 0, "draws": 0}
    assert err.splitlines()[-1] == "match 1 was cancelled (1 leg unplayed)"


def test_a_leg_without_a_result_exits_3(server, teams, said, capsys):
    """A leg that ended without a result (every side forfeited) makes ``labd match
    --wait`` exit 3 (error), naming the leg; the score counts the other legs."""
    service = server.lab.service
    a, b = (str(teams[n].path) for n in "ab")
    with in_background("match", a, b, "--task", TASK, "--seeds", "1", "--wait") as done:
        assert next_line(said).startswith("match 1 queued: ")
        next_line(said)
        play(service, ("", "forfeit", (0, 0), "home,away"), ("home", "goal", (1, 0)))
        code = done.result(WAIT)
    out, err = capsys.readouterr()
    assert code == ExitCode.ERROR, out + err
    assert err.splitlines()[-1] == (
        "match 1: 1 leg ended without a result (leg 0): the score counts only the others"
    )
    assert "  leg 0, seed 0, A at home: no result (error): no result, every side forfeited" in (
        out.splitlines()
    )
    assert "  leg 1, seed 0, B at home: B won 1-0 (goal)" in out.splitlines()
    assert "  score: A 0, B 1, 0 drawn" in out.splitlines()


@pytest.mark.parametrize(
    ("argv", "error"),
    [
        pytest.param(["match", "A", "B", "--task", "nope"], "nope", id="unknown-task"),
        pytest.param(
            ["match", "A", "B", "--task", "icreate-maze"],
            "icreate-maze is not played by two teams",
            id="task-without-sides",
        ),
        pytest.param(["ladder", "nope"], "nope", id="ladder-of-unknown-task"),
        pytest.param(
            ["ladder", "icreate-maze"],
            "icreate-maze is not played by two teams: it has no ladder (HTTP 404)",
            id="ladder-of-task-without-sides",
        ),
    ],
)
def test_a_request_the_lab_refuses_exits_2_with_its_reason(server, teams, capsys, argv, error):
    """An unknown task, or one not played by two teams, is refused by the lab: the
    command exits 2 (usage) with the lab's reason, on stderr or as JSON."""
    argv = [str(teams[w.lower()].path) if w in ("A", "B") else w for w in argv]
    code, out, err = run(capsys, *argv)
    assert code == ExitCode.USAGE
    assert out == ""
    assert err.startswith(f"labd {argv[0]}: ") and error in err, err
    code, out, _ = run(capsys, *argv, "--json")
    assert code == ExitCode.USAGE
    assert error in json.loads(out)["error"]


def test_a_wrong_number_of_seeds_is_a_usage_error(capsys):
    """``--seeds 0`` is refused by the command line itself (exit 2), saying the range."""
    with pytest.raises(SystemExit) as exited:
        main(["match", "a", "b", "--task", TASK, "--seeds", "0"])
    assert exited.value.code == ExitCode.USAGE
    assert "a match plays 1 to 50 seeds" in capsys.readouterr().err


def test_matches_lists_newest_first_and_filters(server, teams, capsys, tmp_path, monkeypatch):
    """``labd matches`` is a table of every match, newest first (id, task, A, B, the
    score, status, verified); ``--repository`` (a relative folder, as ``match`` took
    it), ``--commit`` (its first digits) and ``--task`` narrow it."""
    service = server.lab.service
    a, b, c = teams["a"], teams["b"], teams["c"]
    for other in (b, c):
        assert (
            run(capsys, "match", str(a.path), str(other.path), "--task", TASK, "--seeds", "1")[0]
            == 0
        )
    play(service, ("home", "goal", (1, 0)), ("draw", "time"))  # the first match: A 1, 1 drawn
    code, out, err = run(capsys, "matches")
    assert code == 0, err
    header, *rows = out.splitlines()
    assert header.split() == ["ID", "TASK", "A", "B", "A-B-DRAWN", "STATUS", "VERIFIED"]
    assert [row.split()[0] for row in rows] == ["2", "1"]
    assert rows[0].split()[-3:] == ["0-0-0", "queued", "no"]
    assert rows[1].split()[-3:] == ["1-0-1", "finished", "yes"]
    assert f"{short(a)}  {short(c)}" in rows[0]

    monkeypatch.chdir(tmp_path)
    code, out, _ = run(capsys, "matches", "--repository", "team-c", "--json")
    assert [m["id"] for m in json.loads(out)["matches"]] == [2]
    b_commit = b.git("rev-parse", "HEAD").strip()
    code, out, _ = run(capsys, "matches", "--commit", b_commit[:8], "--json")
    assert [m["id"] for m in json.loads(out)["matches"]] == [1]
    assert run(capsys, "matches", "--task", "soccer-2v2")[1] == "no matches\n"


def test_the_ladder_ranks_the_strongest_first(server, teams, capsys):
    """``labd ladder TASK`` ranks commits best first (rank, repository, commit, rating,
    95 % interval, matches, W-L-D): A beat B and C, B beat C."""
    service = server.lab.service
    a, b, c = teams["a"], teams["b"], teams["c"]
    code, out, _ = run(capsys, "ladder", TASK)
    assert code == 0
    assert out.startswith(f"{TASK}: no commit rated yet")
    for first, second in ((a, b), (b, c), (a, c)):
        assert (
            run(capsys, "match", str(first.path), str(second.path), "--task", TASK, "--seeds", "1")[
                0
            ]
            == 0
        )
        # A's side wins both legs: at home (leg 0), then away (leg 1)
        play(service, ("home", "goal", (1, 0)), ("away", "goal", (0, 1)))
    code, out, err = run(capsys, "ladder", TASK)
    assert code == 0, err
    header, *rows = out.splitlines()
    assert header.split()[:3] == ["RANK", "REPOSITORY", "COMMIT"]
    cells = [row.split() for row in rows]
    assert [(r[0], r[1], r[2], r[-2], r[-1]) for r in cells] == [
        ("1", str(a.path.resolve()), a.git("rev-parse", "HEAD").strip()[:12], "2", "4-0-0"),
        ("2", str(b.path.resolve()), b.git("rev-parse", "HEAD").strip()[:12], "2", "2-2-0"),
        ("3", str(c.path.resolve()), c.git("rev-parse", "HEAD").strip()[:12], "2", "0-4-0"),
    ]
    code, out, _ = run(capsys, "ladder", TASK, "--json")
    ratings = [row["rating"] for row in json.loads(out)["rows"]]
    assert ratings == sorted(ratings, reverse=True) and ratings[0] > ratings[-1]
    assert [int(r[3]) for r in cells] == [round(x) for x in ratings]


def test_joining_the_ladder_queues_the_matches_it_is_given(server, teams, capsys):
    """``labd ladder join REPO --task TASK``: the first entry waits for others, the next
    plays it; a join without a task, or a ladder asked with two words, is a usage error."""
    a, b = teams["a"], teams["b"]
    code, out, err = run(capsys, "ladder", "join", str(a.path), "--task", TASK)
    assert code == 0, err
    assert out.startswith(f"entered on the {TASK} ladder (entry 1): the first one;")
    code, out, err = run(capsys, "ladder", "join", str(b.path), "--task", TASK)
    assert code == 0, err
    first, second = out.splitlines()
    assert first == f"{short(b)} entered on the {TASK} ladder (entry 2): 1 match queued"
    assert second.startswith(f"  match 1 against {short(a)}: http")
    code, out, _ = run(capsys, "ladder", "join", str(a.path), "--task", TASK, "--json")
    joined = json.loads(out)
    assert (joined["entry"], [m["b"]["repository"] for m in joined["matches"]]) == (
        1, [str(b.path.resolve())]
    )  # fmt: skip
    assert run(capsys, "ladder", "join", str(a.path))[0] == ExitCode.USAGE
    code, _, err = run(capsys, "ladder", TASK, "extra")
    assert code == ExitCode.USAGE and "labd ladder TASK shows a ladder" in err
    code, _, err = run(capsys, "ladder", "join", str(a.path), "--task", "icreate-maze")
    assert code == ExitCode.USAGE and "icreate-maze is not played by two teams" in err


@pytest.mark.parametrize(
    ("ours", "theirs"),
    [
        (command.MatchView, api.MatchView),
        (command.MatchPage, api.MatchPage),
        (command.Ladder, api.Ladder),
        (command.Joined, api.JoinedView),
    ],
)
def test_the_command_reads_the_bodies_the_api_writes(ours, theirs):
    """The command's copies of the API's bodies (it may not import FastAPI) have the
    same fields of the same types, all the way down."""
    assert shape(ours.model_json_schema()) == shape(theirs.model_json_schema())


def test_the_commands_start_without_the_lab_s_machinery():
    """``labd match``, ``matches`` and ``ladder`` are client commands: their module loads
    none of the simulator, the database, the web server, numpy or pyarrow."""
    seen = loaded("labd.commands.match")
    assert {"labd.commands.match", "scheduler.client", "httpx"} <= seen
    assert (LAB | {"numpy", "pyarrow"}) & seen == set()


def shape(schema: Any) -> Any:
    """A JSON schema without its words (titles and descriptions)."""
    if isinstance(schema, dict):
        return {k: shape(v) for k, v in schema.items() if k not in ("title", "description")}
    if isinstance(schema, list):
        return [shape(v) for v in schema]
    return schema
