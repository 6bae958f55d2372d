"""The benchmark leaderboard (``repository.benchmark_run.leaderboard``): each commit's first
run, never its best, ranked by IQM once finished and verified, the rest unranked after."""

from __future__ import annotations

import datetime as dt
from typing import Any

from repository.benchmark_run import BenchmarkRun, leaderboard
from repository.trial import Status

NOW = dt.datetime(2026, 1, 1, tzinfo=dt.UTC)


def run(id_: int, commit: str, iqm: float | None, **fields: Any) -> BenchmarkRun:
    values: dict[str, Any] = {
        "id": id_,
        "benchmark": "dmc-classic",
        "suite": "",
        "repository": f"/repos/{commit}",
        "ref": None,
        "commit": commit * 40,
        "submitter": "rita",
        "status": Status.FINISHED,
        "created": NOW,
        "finished": NOW,
        "evaluations": [],
        "episodes": 120,
        "done": 120,
        "iqm": iqm,
        "iqm_interval": None if iqm is None else (iqm - 0.05, iqm + 0.05),
        "mean": iqm,
        "verified": True,
    }
    return BenchmarkRun(**{**values, **fields})


def test_each_commit_is_ranked_by_its_first_run_and_the_rest_follow_unranked():
    """Finished verified first runs rank by IQM (overlapping intervals marked as ties);
    a commit's later, better run is not on the board; a first run that is unverified,
    cancelled or still running is listed unranked with why, after the ranked ones."""
    rows = leaderboard(
        [
            run(1, "a", 0.40),
            run(2, "b", 0.70),
            run(3, "a", 0.95),  # a's second run: luckier, and not on the board
            run(4, "c", 0.90, verified=False),
            run(5, "d", 0.42),
            run(6, "e", None, status=Status.CANCELLED, done=30, verified=False),
            run(7, "e", 0.99),  # e's first was cancelled: that one stays its row
            run(8, "f", None, status=Status.RUNNING, finished=None, done=10, verified=False),
        ]
    )
    assert [(r.rank, r.run) for r in rows] == [
        (1, 2), (2, 5), (3, 1), (None, 4), (None, 6), (None, 8),
    ]  # fmt: skip
    assert [r.tie for r in rows[:3]] == [False, False, True]  # 0.42 ± .05 overlaps 0.40 ± .05
    assert all(r.note is None for r in rows[:3])
    notes = [r.note or "" for r in rows[3:]]
    assert "not all verified" in notes[0]
    assert notes[1].startswith("not ranked: cancelled")
    assert notes[2].startswith("not ranked: still running")
    assert {r.commit[0] for r in rows} == set("abcdef") and len(rows) == 6
    top = rows[0]
    assert (top.iqm, top.mean, top.episodes, top.status) == (0.70, 0.70, 120, Status.FINISHED)
    assert top.iqm_interval == (0.70 - 0.05, 0.70 + 0.05) and top.verified


def test_no_runs_no_rows():
    """An empty board is empty."""
    assert leaderboard([]) == []
