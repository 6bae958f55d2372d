"""The playground's trials on a worker that reaches the lab at another address than the
one people reach it at (a compose network's ``http://lab:8080`` against the host's
published port).

The lab records a playground repository under its public URL (``--public-url``, here a
name that resolves nowhere, as a published port does not lead back into a container);
the lab fetches it from the port it listens on, and a remote worker (``labd worker
--server``, the default fetch policy: no http, no private hosts) from its own
``--server``, as the lab's hello tells it the public prefix. The record names the public
repository whichever worker ran it, and the data digest is the same.
"""

from __future__ import annotations

import signal
import subprocess
import sys
from pathlib import Path

import httpx
import pytest

from labd.playground import template
from scheduler.fetch import mirror_path
from tests.faults.conftest import Served
from tests.helpers.labs import shared_cache

pytestmark = [pytest.mark.integration, pytest.mark.timeout(400)]
PUBLIC = "http://lab.invalid:8080"  # RFC 6761: .invalid resolves nowhere
# The maze's starting script, ending after 40 ticks (its outcome is then "fail": the
# controller left before the episode's end; what matters is where it ran, and its data).
SHORT = (
    template("icreate-maze")
    .replace("  if (!(await tick())) break;", "  if (!(await tick()) || ++ticks >= 40) break;")
    .replace("let bumps = 0;", "let bumps = 0;\nlet ticks = 0;")
)


class RemoteWorker:
    """``labd worker --server URL`` with its own data folder and mirrors (the session's
    controller runtime linked in), under the default fetch policy."""

    def __init__(self, server: str, token: str, data: Path, cache: Path) -> None:
        shared_cache(data, cache)
        self.cache = data / "cache"
        self.process = subprocess.Popen(
            [sys.executable, "-m", "labd", "--log-level", "INFO", "worker", "--server", server,
             "--token", token, "--sandbox", "bwrap", "--data", str(data), "--poll", "0.2"],
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True,
        )  # fmt: skip

    def stop(self) -> str:
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGTERM)
            try:
                self.process.wait(60)
            except subprocess.TimeoutExpired:
                self.process.kill()
        output, _ = self.process.communicate(timeout=30)
        return output


def test_a_playground_trial_runs_on_a_worker_that_reaches_the_lab_elsewhere(cache, tmp_path):
    """A playground commit recorded under a public URL that leads nowhere runs on the
    lab's own worker, and its rerun on a remote worker that reaches the lab at its real
    address reproduces it: the same public repository in both records, the same data
    digest, the worker's mirror named by the public URL."""
    lab_cache = tmp_path / "lab"
    shared_cache(lab_cache, cache)
    lab = Served(
        tmp_path / "data",
        lab_cache / "cache",
        "--no-robots", "--workers", "1", "--sandbox", "bwrap", "--public-url", PUBLIC,
    )  # fmt: skip
    lab.token = lab.add_user("alice")
    worker_token = lab.add_user("w1", "--worker")
    worker: RemoteWorker | None = None
    try:
        lab.start()
        body = {"name": "pg1", "task": "icreate-maze", "script": SHORT, "seed": 3}
        made = httpx.post(
            f"{lab.server}/api/playground/trials",
            json=body,
            headers={"Authorization": f"Bearer {lab.token}"},
            timeout=120,
        )
        assert made.status_code == 201, made.text
        repository = f"{PUBLIC}/git/alice/pg1.git"
        assert made.json()["repository"] == repository
        [here] = lab.wait_ended([made.json()["trial"]["id"]], 180)
        assert here["outcome"] == "fail" and "before the episode ended" in here["reason"], here
        assert "/local-" in here["worker"], here["worker"]

        # the same lab with no worker of its own, and one elsewhere
        lab.stop()
        lab.args[lab.args.index("--workers") + 1] = "0"
        lab.start()
        worker = RemoteWorker(lab.server, worker_token, tmp_path / "worker", cache)
        again = httpx.post(
            f"{lab.server}/api/trials/{here['id']}/rerun",
            headers={"Authorization": f"Bearer {lab.token}"},
            timeout=60,
        )
        assert again.status_code == 201, again.text
        [there] = lab.wait_ended([again.json()["id"]], 180)
    finally:
        said = worker.stop() if worker is not None else ""
        lab.stop()
    assert there["outcome"] == "fail", (there["reason"], said)
    assert there["worker"].startswith("w1@"), there["worker"]
    assert there["reproduced"] is True, there["verdict"]
    assert there["data_digest"] == here["data_digest"]
    assert there["repository"] == here["repository"] == repository
    assert there["manifest"]["repository"] == repository
    assert mirror_path(worker.cache, repository).is_dir()  # fetched by the worker itself
