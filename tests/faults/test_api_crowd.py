"""200 requests to the HTTP API at once, reads and writes mixed, on a lab that is running
trials: every one is answered as it would be alone, and none with a 5xx.
"""

from __future__ import annotations

import asyncio
import hashlib
import random
import time
from pathlib import Path

import httpx
import pytest

from tests.helpers.githttp import GitRepo

pytestmark = [pytest.mark.integration, pytest.mark.rates]

QUICK = """\
from controllers.client import Lab
with Lab.connect() as lab:
    for _ in range(3):
        lab.step()
"""
FILES = {
    "lab.toml": '[controller]\ncommand = ["python", "c.py"]\ntask = "icreate-maze"\n',
    "c.py": QUICK,
}


@pytest.mark.timeout(240)
def test_200_concurrent_api_requests(served, database_url: str, tmp_path: Path):
    """Submissions, reruns, cancels, refusals, lists, records and downloads, 200 at once:
    each gets the answer it would get alone, none a 5xx, and every write lands once
    (on SQLite and on PostgreSQL)."""
    lab = served(
        "--no-robots", "--workers", "1", "--sandbox", "bwrap", "--database", database_url,
        "--allow-local-repos",
    )  # fmt: skip
    lab.token = lab.add_user("alice", "--max-running", "1", "--max-daily", "1000")
    lab.start()
    repo = GitRepo.create(tmp_path / "quick", FILES)
    commit = repo.rev()
    first = lab.submit(repo.path)
    [done] = lab.wait_ended([first["id"]], 120)
    assert done["outcome"] == "fail", done  # three steps, then it stops: not the goal
    queued = [lab.submit(repo.path, seed=100 + n)["id"] for n in range(20)]
    before = lab.get("/api/trials?limit=500")["trials"]
    figures = asyncio.run(burst(lab, repo.path, commit, done, queued))
    print(
        f"200 API requests: all answered in {figures['seconds']:.1f} s, "
        f"p50 {figures['p50']:.2f} s, max {figures['max']:.2f} s; statuses {figures['statuses']}"
    )
    after = lab.get("/api/trials?limit=500")["trials"]
    made = figures["made"]
    assert len(set(made)) == len(made) == 50 + 20
    assert {t["id"] for t in after} == {t["id"] for t in before} | set(made)
    for trial in after:
        if trial["id"] in made:
            assert trial["commit"] == commit
    assert lab.process.poll() is None, lab.log


async def burst(lab, repo: Path, commit: str, done: dict, queued: list[int]) -> dict:
    auth = {"Authorization": f"Bearer {lab.token}"}
    first = done["id"]
    digest = done["mcap"]["digest"]
    requests = (
        [("POST", "/api/trials", {"repository": str(repo), "seed": n}, 201) for n in range(50)]
        + [("POST", f"/api/trials/{first}/rerun", None, 201)] * 20
        + [("POST", f"/api/trials/{i}/cancel", None, 200) for i in queued]
        + [("POST", "/api/trials", {"repository": str(repo), "task": "nope"}, 422)] * 5
        + [("POST", "/api/trials", {"repository": str(repo), "ref": "no-such-branch"}, 422)] * 5
        + [("GET", "/api/trials?limit=20", None, 200)] * 30
        + [("GET", f"/api/trials/{first}", None, 200)] * 30
        + [("GET", f"/api/trials/{first}/data.mcap", None, 200)] * 20
        + [("GET", f"/api/commits/{commit[:10]}", None, 200)] * 10
        + [("GET", "/api/tasks", None, 200)] * 5
        + [("GET", "/api/status", None, 200)] * 5
    )
    assert len(requests) == 200
    random.Random(7).shuffle(requests)
    limits = httpx.Limits(max_connections=200, max_keepalive_connections=0)
    async with httpx.AsyncClient(base_url=lab.server, limits=limits, timeout=120) as client:
        gate = asyncio.Event()

        async def one(method: str, path: str, body: dict | None, expected: int):
            await gate.wait()
            start = time.monotonic()
            headers = auth if method == "POST" else {}
            answer = await client.request(method, path, json=body, headers=headers)
            return method, path, body, expected, answer, time.monotonic() - start

        tasks = [asyncio.create_task(one(*r)) for r in requests]
        await asyncio.sleep(0)  # every request waits at the gate ...
        began = time.monotonic()
        gate.set()  # ... and all go at once
        results = await asyncio.gather(*tasks)
        seconds = time.monotonic() - began
    made, statuses, times = [], {}, []
    for method, path, body, expected, answer, took in results:
        statuses[answer.status_code] = statuses.get(answer.status_code, 0) + 1
        times.append(took)
        assert answer.status_code < 500, (method, path, answer.status_code, answer.text)
        assert answer.status_code == expected, (method, path, body, answer.status_code, answer.text)
        if path.endswith("data.mcap"):
            assert "sha256:" + hashlib.sha256(answer.content).hexdigest() == digest
        elif expected == 201:
            trial = answer.json()
            assert trial["commit"] == commit and trial["status"] in ("queued", "running"), trial
            made.append(trial["id"])
        elif path.endswith("/cancel"):
            assert answer.json()["done"] in ("cancelled", "stopping", "ended"), answer.text
        elif expected == 422:
            assert answer.json()["error"], answer.text
        elif path.startswith("/api/trials?"):
            assert answer.json()["trials"], answer.text
        elif path.startswith("/api/trials/"):
            assert answer.json()["id"] == first
        elif path.startswith("/api/commits/"):
            assert first in [t["id"] for t in answer.json()["trials"]], answer.text
    times.sort()
    return {
        "made": made,
        "statuses": statuses,
        "seconds": seconds,
        "p50": times[len(times) // 2],
        "max": times[-1],
    }
