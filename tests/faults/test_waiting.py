"""`labd submit --wait` says where its trial is while it waits: its place in the queue,
then the worker that runs it."""

from __future__ import annotations

import os
import queue
import re
import subprocess
import sys
import threading

from tests.faults.conftest import wait_for
from tests.faults.slow import Held, controller
from tests.helpers.githttp import GitRepo
from tests.helpers.timing import SECOND


def test_submit_wait_shows_the_queue_then_the_worker(served, tmp_path):
    lab = served("--no-robots", "--workers", "1", "--sandbox", "bwrap", "--allow-local-repos")
    lab.token = lab.add_user("alice", "--max-running", "1")
    lab.start()
    held = Held()  # the first trial runs until the third is seen queued behind it
    first = lab.submit(GitRepo.create(tmp_path / "held", held.files).path, params=held.params)
    second = lab.submit(GitRepo.create(tmp_path / "second", controller(3)).path)
    third = GitRepo.create(tmp_path / "third", controller(30, 0.1)).path
    assert lab.trial(second["id"])["queued_ahead"] in (0, 1)  # the first may have started

    def running_first() -> str | None:
        said = lab.labd("status").stdout
        return said if f"trial {first['id']} (icreate-maze) on " in said else None

    said = wait_for("labd status to show the lab's own worker's trial", running_first, 60 * SECOND)
    assert re.search(r"\d queued, 1 running; 1 worker in the lab", said), said
    waiting = subprocess.Popen(
        [sys.executable, "-m", "labd", "submit", str(third), "--ref", "main", "--task",
         "icreate-maze", "--wait"],
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
        env={**os.environ, "LABD_SERVER": lab.server, "LABD_TOKEN": lab.token},
    )  # fmt: skip
    lines: queue.Queue[str] = queue.Queue()

    def read() -> None:
        for line in waiting.stderr:
            lines.put(line)

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    said = []
    try:
        while not any("queued," in line for line in said):  # it says so while it waits
            said.append(lines.get(timeout=120 * SECOND))
    finally:
        assert held.let_go() == 1
    assert waiting.wait(300 * SECOND) == 1, said  # it ran to its end (a few steps: no goal)
    reader.join(30 * SECOND)
    waiting.stderr.close()
    while not lines.empty():
        said.append(lines.get())
    said = [line.rstrip("\n") for line in said]
    queued = [line for line in said if "queued," in line]
    assert re.search(r"queued, (next|[12] submitted before it still waiting)$", queued[0]), said
    assert any(re.search(r": running on \S+", line) for line in said), said
    assert lab.trial(first["id"])["queued_ahead"] is None  # only a queued trial has a place
