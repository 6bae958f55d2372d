"""A third-party task package, installed as an operator would: the documented example
(docs/examples/labd-puck) is built and installed into a throwaway folder of packages,
and every labd that sees that folder (PYTHONPATH) has the task: `labd tasks` lists it,
`labd run` runs it, `labd serve` hosts it (a trial, its export, its replay, its pages,
a live robot of it). A second plugin that fails to import is reported, and every other
task still works.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import httpx
import pytest

from tests.helpers.githttp import GitRepo
from tests.helpers.labs import shared_cache
from tests.helpers.sandboxes import make_backend

pytestmark = [pytest.mark.integration, pytest.mark.timeout(300)]
EXAMPLE = Path(__file__).resolve().parents[2] / "docs" / "examples" / "labd-puck"
BROKEN = """\
[build-system]
requires = ["setuptools>=61"]
build-backend = "setuptools.build_meta"

[project]
name = "labd-broken"
version = "0.1.0"

[project.entry-points."labd.tasks"]
broken = "labd_broken:TASK"

[tool.setuptools]
py-modules = ["labd_broken"]
"""
CONTROLLER = """\
import math
from controllers.client import EpisodeOver, Lab

with Lab.connect() as lab:
    pose = lab.subscribe("/pose", "geometry_msgs/msg/PointStamped")
    goal = lab.subscribe("/goal", "geometry_msgs/msg/PointStamped").get()
    try:
        while True:
            here = pose.latest["point"] if pose.latest else {"x": 0.0, "y": 0.0}
            dx, dy = goal["point"]["x"] - here["x"], goal["point"]["y"] - here["y"]
            scale = min(1.0, 3 * math.hypot(dx, dy)) / max(math.hypot(dx, dy), 1e-9)
            lab.publish("/cmd_vel", "geometry_msgs/msg/Twist",
                        {"linear": {"x": dx * scale, "y": dy * scale}})
            lab.step()
    except EpisodeOver:
        pass
"""


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> Path:
    """The example package and a broken one, built and installed into a folder."""
    root = tmp_path_factory.mktemp("plugins")
    shutil.copytree(EXAMPLE, root / "labd-puck")
    broken = root / "labd-broken"
    broken.mkdir()
    (broken / "pyproject.toml").write_text(BROKEN)
    (broken / "labd_broken.py").write_text('raise RuntimeError("this plugin is broken")\n')
    target = root / "site"
    for package in (root / "labd-puck", broken):
        subprocess.run(
            [sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--no-build-isolation",
             "--target", str(target), str(package)],
            check=True, capture_output=True, timeout=180,
        )  # fmt: skip
    return target


def labd(site: Path, *args: str, timeout: float = 180) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONPATH": str(site)}
    return subprocess.run(
        [sys.executable, "-m", "labd", *args],
        capture_output=True, text=True, env=env, timeout=timeout, check=False,
    )  # fmt: skip


def test_labd_tasks_lists_the_plugin_and_reports_the_broken_one(site):
    """`labd tasks --local` lists puck beside the lab's own tasks, and the broken
    plugin as left out, with its error; without the folder there is no puck."""
    done = labd(site, "tasks", "--local", "--json")
    assert done.returncode == 0, done.stderr
    listing = json.loads(done.stdout)
    names = [t["name"] for t in listing["tasks"]]
    assert {"puck", "icreate-maze", "pr2-table"} <= set(names)
    assert [p["plugin"] for p in listing["problems"]] == ["broken = labd_broken:TASK"]
    assert "RuntimeError: this plugin is broken" in listing["problems"][0]["problem"]
    text = labd(site, "tasks", "--local").stdout
    assert "left out: the task plugin broken = labd_broken:TASK: failed to import" in text
    alone = json.loads(labd(site.parent / "nowhere", "tasks", "--local", "--json").stdout)
    assert "puck" not in [t["name"] for t in alone["tasks"]]


def test_labd_run_and_serve_run_the_plugin_task(site, cache, tmp_path):
    """labd run runs a controller on puck to success; labd serve hosts it: a submitted
    trial succeeds and is exported and replayed, its task and trial pages and a live
    robot of it are served, /api/tasks reports the broken plugin."""
    make_backend("bwrap", cache)
    data = tmp_path / "data"
    shared_cache(data, cache)
    repo = GitRepo.create(
        tmp_path / "pusher",
        {
            "lab.toml": '[controller]\ncommand = ["python", "c.py"]\ntask = "puck"\n',
            "c.py": CONTROLLER,
        },
    )
    ran = labd(
        site,
        "run",
        str(repo.path),
        "--sandbox",
        "bwrap",
        "--data",
        str(data),
        "--seed",
        "2",
        "--json",
    )
    result = json.loads(ran.stdout)
    assert (result["outcome"], ran.returncode) == ("success", 0), result["reason"]

    token = labd(site, "users", "add", "alice", "--data", str(data)).stdout.split()[0]
    env = {**os.environ, "PYTHONPATH": str(site)}
    server = subprocess.Popen(
        [sys.executable, "-m", "labd", "serve", "--data", str(data), "--http-port", "0",
         "--bridge-port", "0", "--robot", "puck-1=puck", "--sandbox", "bwrap",
         "--allow-local-repos"],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env,
    )  # fmt: skip
    try:
        said = []
        assert server.stdout is not None
        for line in server.stdout:
            said.append(line)
            if found := re.search(r"HTTP API on (http://\S+)/api", line):
                http = found.group(1)
                break
        else:
            pytest.fail("".join(said))
        assert any("task plugin left out: broken = labd_broken:TASK" in s for s in said), said
        submitted = labd(site, "submit", str(repo.path), "--seed", "3", "--wait", "--json",
                         "--server", http, "--token", token)  # fmt: skip
        trial = json.loads(submitted.stdout)
        assert (trial["task"], trial["outcome"]) == ("puck", "success"), submitted.stdout

        out = tmp_path / "export"
        exported = labd(
            site,
            "export",
            str(trial["id"]),
            "--format",
            "parquet",
            "-o",
            str(out),
            "--server",
            http,
        )
        assert exported.returncode == 0, exported.stdout + exported.stderr
        assert any(out.rglob("*.parquet"))
        replayed = labd(site, "replay", str(trial["id"]), "--server", http, "--json")
        assert json.loads(replayed.stdout)["verified"] is True, replayed.stdout

        with httpx.Client(base_url=http, timeout=30) as client:
            assert "pushed by a velocity command" in client.get("/tasks/puck").text
            assert client.get(f"/trials/{trial['id']}").status_code == 200
            assert client.get("/robots/puck-1").status_code == 200
            problems = client.get("/api/tasks").json()["problems"]
            assert [p["plugin"] for p in problems] == ["broken = labd_broken:TASK"]
    finally:
        server.terminate()
        server.communicate(timeout=60)  # and its pipe is closed
