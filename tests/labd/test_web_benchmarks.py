"""The benchmarks' pages in process: a benchmark's leaderboard (each commit's first run,
ranked by IQM once finished and verified; an unverified one unranked; a second run of a
commit not on it), its runs' IQMs and intervals in words and as bars, the top runs'
performance profiles, a run's page with its numbers and tasks, a repository named with
HTML shown escaped, and the 404 pages.

Runs are submitted through the API to real git repositories; no workers run, so episodes
are claimed and filed the way a worker files them (``test_api_benchmark_runs``).
"""

# ruff: noqa: F811 (the API's fixtures, imported from test_api, are the tests' arguments)
from __future__ import annotations

from typing import Any

from markupsafe import escape

from labd.web.benchmarks import spread
from labd.web.evaluations import rounded
from repository.trial import Filing
from tests.labd.test_api import service  # noqa: F401 (fixtures)
from tests.labd.test_api_benchmark_runs import CLASSIC, DEV, controller, file_all, run
from tests.labd.test_web_evaluations import Elements, web, writer  # noqa: F401 (fixtures)

HTML_NAME = "<b>bold</b> & co"  # a repository's directory: the pages show it, never parse it


async def submitted(web: Any, token: str, repository: str) -> dict[str, Any]:
    reply = await run(web, token, repository)
    assert reply.status_code == 201, reply.text
    return reply.json()


def file_unverified(service: Any, reward: float) -> None:
    """Claim every queued episode and file it with ``reward``, its replay not verified."""
    service.queue.check = None
    while (claim := service.queue.claim("w")) is not None:
        filing = Filing(
            status="finished",
            outcome="success" if reward >= 900 else "fail",
            reason=f"a return of {reward}",
            data_digest=f"{claim.id:064x}",
            metrics={"reward": reward},
        )
        assert service.queue.finish(claim.id, "w", filing)


async def test_the_leaderboard_ranks_first_runs_by_iqm_and_the_pages_show_them(
    web, service, writer, tmp_path
):
    """Two finished verified runs rank by IQM; an unverified one follows unranked; a
    commit's second, better run is not on the board; the benchmark's page shows each
    IQM with its interval in words and as a bar, the profiles of the top runs and the
    HTML-named repository escaped; a run's page shows its numbers, a row per task linked
    to its evaluation, and follows it only while it runs."""
    strong, weak = controller(tmp_path, "strong"), controller(tmp_path, HTML_NAME)
    unchecked = controller(tmp_path, "unchecked")
    first = await submitted(web, writer, strong)
    file_all(service, lambda claim: 800.0 + 40 * (claim.id % 5))
    second = await submitted(web, writer, weak)
    file_all(service, lambda claim: 300.0 + 50 * (claim.id % 7))
    again = await submitted(web, writer, strong)  # the same commit, luckier
    file_all(service, lambda claim: 1000.0)
    apart = await submitted(web, writer, unchecked)
    running = await web.get(f"/benchmark-runs/{apart['id']}")
    assert running.status_code == 200 and "/static/benchmark-run.js" in running.text
    assert Elements(running.text).by_id("benchmark-run")["data-status"] == "queued"
    file_unverified(service, 990.0)

    body = (await web.get("/api/benchmarks/dmc-classic")).json()
    board = body["leaderboard"]
    assert [(r["rank"], r["run"]) for r in board] == [
        (1, first["id"]), (2, second["id"]), (None, apart["id"]),
    ]  # fmt: skip
    assert again["id"] not in {r["run"] for r in board}
    assert board[0]["iqm"] > board[1]["iqm"] and board[2]["iqm"] > board[0]["iqm"]
    assert board[2]["note"].startswith("not ranked:") and not board[2]["verified"]

    answer = await web.get("/benchmarks/dmc-classic")
    assert answer.status_code == 200
    html = answer.text
    found = Elements(html)
    rows = [e for e in found.having("data-run") if e["tag"] == "tr"]
    assert [int(r["data-run"]) for r in rows] == [r["run"] for r in board]
    for row, said in zip(rows, board, strict=True):
        assert rounded(said["iqm"], 3) in row["text"]
        assert spread(tuple(said["iqm_interval"])) in row["text"]
        assert said["commit"][:10] in row["text"]
    assert rows[0]["text"].strip().startswith("1") and rows[2].get("class") == "unranked"
    bars = [e for e in found.found if e["tag"] == "rect" and e.get("class") == "point"]
    assert len(bars) == 3
    assert str(escape(HTML_NAME)) in html and HTML_NAME not in html
    curves = [e for e in found.found if e["tag"] == "path" and "curve" in e.get("class", "")]
    assert [int(c["data-run"]) for c in curves] == [r["run"] for r in board]
    assert all(c["d"].startswith("M") for c in curves)
    assert "stratified bootstrap" in html and "labd evaluate REPO --benchmark dmc-classic" in html
    assert "POST /api/benchmark-runs" in html and 'style="' not in html
    tasks = [e["href"] for e in found.having("href") if e["href"].startswith("/tasks/")]
    assert "/tasks/dmc-cartpole-balance" in tasks

    shown = await web.get(f"/benchmark-runs/{first['id']}")
    assert shown.status_code == 200 and "/static/benchmark-run.js" not in shown.text
    made = (await web.get(f"/api/benchmark-runs/{first['id']}")).json()
    page = Elements(shown.text)
    numbers = {e["data-number"]: e["text"] for e in page.having("data-number")}
    for name, key in (("IQM", "iqm"), ("mean", "mean"), ("median", "median")):
        assert rounded(made[key], 3) in numbers[name]
        assert spread(tuple(made[f"{key}_interval"])) in numbers[name]
    lines = {e["data-task"]: e["text"] for e in page.having("data-task")}
    assert len(lines) == CLASSIC
    for task in made["evaluations"]:
        assert f"#{task['evaluation']}" in lines[task["task"]]
        assert f"{DEV} of {DEV}" in lines[task["task"]]
        assert rounded(task["normalized_mean"], 3) in lines[task["task"]]
    links = {e["href"] for e in page.having("href")}
    assert {f"/evaluations/{t['evaluation']}" for t in made["evaluations"]} <= links
    assert "/benchmarks/dmc-classic" in links and f"/commits/{first['commit']}" in links
    assert "✓ verified" in page.by_id("verified")["text"]
    assert page.by_id("signed")["text"].startswith(("signed by the lab", "not signed"))
    assert len([e for e in page.found if e["tag"] == "path"]) == 1
    escaped = (await web.get(f"/benchmark-runs/{second['id']}")).text
    assert str(escape(HTML_NAME)) in escaped and HTML_NAME not in escaped


async def test_an_empty_board_says_how_to_run_one_and_unknowns_are_404_pages(web):
    """A benchmark without runs says how to run one, and its tasks' pages link it; an
    unknown benchmark is a 404 page naming the known ones; an unknown run is the API's
    404, as a page."""
    empty = await web.get("/benchmarks/dmc")
    assert empty.status_code == 200
    assert "labd evaluate REPO --benchmark dmc" in Elements(empty.text).by_id("empty")["text"]
    task = Elements((await web.get("/tasks/dmc-cartpole-balance")).text)
    assert "dmc-classic, dmc" in task.by_id("benchmark-links")["text"]
    links = {e["href"] for e in task.having("href")}
    assert {"/benchmarks/dmc-classic", "/benchmarks/dmc"} <= links
    assert "benchmark-links" not in (await web.get("/tasks/soccer-1v1")).text
    missing = await web.get("/benchmarks/dmc-clasic", headers={"Accept": "text/html"})
    assert missing.status_code == 404 and missing.headers["content-type"].startswith("text/html")
    assert "did you mean dmc-classic?" in missing.text and "dmc-classic, dmc" in missing.text
    lost = await web.get("/benchmark-runs/424242", headers={"Accept": "text/html"})
    assert lost.status_code == 404 and lost.headers["content-type"].startswith("text/html")
