"""`labd submit --wait` says where its trial is while it waits: its place in the queue,
then the worker that runs it."""

from __future__ import annotations

import re

from tests.faults.conftest import wait_for
from tests.faults.slow import controller
from tests.helpers.githttp import GitRepo


def test_submit_wait_shows_the_queue_then_the_worker(served, tmp_path):
    lab = served("--no-robots", "--workers", "1", "--sandbox", "bwrap", "--allow-local-repos")
    lab.token = lab.add_user("alice", "--max-running", "1")
    lab.start()
    slow = GitRepo.create(tmp_path / "slow", controller(40, 0.1)).path
    third = GitRepo.create(tmp_path / "third", controller(30, 0.1)).path
    first = lab.submit(slow)
    second = lab.submit(slow, seed=1)
    assert lab.trial(second["id"])["queued_ahead"] in (0, 1)  # the first may have started

    def running_first() -> str | None:
        said = lab.labd("status").stdout
        return said if f"trial {first['id']} (icreate-maze) on " in said else None

    said = wait_for("labd status to show the lab's own worker's trial", running_first, 60)
    assert re.search(r"\d queued, 1 running; 1 worker in the lab", said), said
    done = lab.labd(
        "submit", str(third), "--ref", "main", "--task", "icreate-maze", "--wait", check=False
    )
    assert done.returncode == 1, done.stderr  # it ran to its end (a few steps: no goal)
    said = done.stderr.splitlines()
    queued = [line for line in said if "queued," in line]
    assert queued, done.stderr
    assert re.search(r"queued, (next|[12] submitted before it still waiting)$", queued[0]), said
    assert any(re.search(r": running on \S+", line) for line in said), said
    assert lab.trial(first["id"])["queued_ahead"] is None  # only a queued trial has a place
