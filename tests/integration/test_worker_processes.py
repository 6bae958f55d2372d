"""`labd serve --worker-processes 2`: trials run by `labd worker` children of the lab,
against its own API, each filed, replayed and verified; a child that dies is started
again; when the lab stops, so do its children."""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

import httpx
import pytest

from tests.integration.test_service import EXAMPLES, make_repo

pytestmark = [pytest.mark.integration, pytest.mark.timeout(300)]


def children(pid: int) -> dict[int, str]:
    """The `labd worker` processes whose parent is ``pid``: pid -> command line."""
    found = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
            command = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode()
        except OSError:
            continue
        parent = int(stat.rsplit(")", 1)[1].split()[1])
        if parent == pid and " labd worker " in command:
            found[int(entry.name)] = command
    return found


def wait_for(what, condition, seconds=90.0):
    deadline = time.monotonic() + seconds
    while not (found := condition()):
        assert time.monotonic() < deadline, f"no {what} within {seconds:g} s"
        time.sleep(0.2)
    return found


def test_trials_run_in_worker_processes_of_the_lab(make_served_lab, tmp_path):
    lab = make_served_lab("--workers", "0", "--worker-processes", "2")
    assert lab.process is not None
    first = wait_for("two worker processes", lambda: len(children(lab.process.pid)) == 2 and children(lab.process.pid))  # fmt: skip
    for command in first.values():
        assert "--token" not in command  # the token is in their environment only
        assert f"--server {lab.server}" in command
    repo = make_repo(tmp_path / "maze", copy=EXAMPLES / "icreate-maze")
    queued = [
        lab.json("submit", str(repo), "--ref", "main", "--task", "icreate-maze", "--seed", str(seed))
        for seed in (1, 2, 3)
    ]  # fmt: skip
    for trial in queued:
        path = f"{lab.server}/api/trials/{trial['id']}/replay"
        verdict = wait_for(
            f"trial {trial['id']}'s replay",
            lambda p=path: (r := httpx.get(p, timeout=30)).status_code == 200 and r.json(),
        )
        assert verdict["verified"] is True, verdict
        shown = lab.json("show", str(trial["id"]))
        assert shown["outcome"] == "success", shown
        _, _, rest = shown["worker"].partition(":")
        assert int(rest.split("/")[0]) in first and rest.endswith("/remote-1"), shown["worker"]

    victim = next(iter(first))
    os.kill(victim, signal.SIGKILL)
    again = wait_for(
        "a new worker process",
        lambda: len(now := children(lab.process.pid)) == 2 and victim not in now and now,
    )
    assert set(again) & set(first) == set(first) - {victim}
    lab.stop()
    for pid in again:
        with pytest.raises(ProcessLookupError):
            os.kill(pid, 0)
