"""One lab per data folder, as an operator meets it: a second `labd serve` or `labd demo`
on a folder in use is refused in one line naming the running lab, and rewrites nothing of
it; `labd demo` stopped with SIGTERM takes its `labd serve` with it."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import httpx
import psutil

from labd.commands.demo import free_port
from labd.datalock import holder
from tests.faults.conftest import gone, wait_for
from tests.integration.test_commands import labd


def test_a_second_lab_on_a_folder_in_use_is_refused_naming_the_first(served, tmp_path):
    lab = served("--no-robots", "--workers", "0").start()
    second = labd(
        "serve", "--data", str(lab.data), "--http-port", "0", "--bridge-port", "0", "--no-robots"
    )
    assert second.returncode == 2, second.stderr
    lines = second.stderr.strip().splitlines()
    assert len(lines) == 1, second.stderr
    assert f"in use by the lab at {lab.server} (pid {lab.pid})" in lines[0]
    assert lab.process is not None and lab.process.poll() is None  # the first goes on
    refused = labd("demo", "--data", str(lab.data), "--exit")
    assert refused.returncode == 2
    assert f"already serves {lab.data} at {lab.server}" in refused.stderr
    assert not (lab.data / "demo").exists()  # nothing of the running lab's rewritten
    restore = labd("restore", str(tmp_path / "a-backup"), "--data", str(lab.data))
    assert restore.returncode == 2
    assert f"a lab serves {lab.data} ({lab.server}): stop it" in restore.stderr
    lab.stop()
    assert holder(lab.data) is None  # the folder is free for the next lab
    again = served("--no-robots", "--workers", "0", data=lab.data).start()
    assert again.server


def test_the_demo_stopped_with_sigterm_stops_its_lab(tmp_path: Path):
    data = tmp_path / "data"
    ports = ["--http-port", str(free_port(0)), "--bridge-port", str(free_port(0))]
    demo = subprocess.Popen(
        [sys.executable, "-m", "labd", "demo", "--data", str(data), "--sandbox", "bwrap", *ports],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )
    try:
        found = wait_for("the demo's lab", lambda: holder(data), timeout=120)
        serve = psutil.Process(int(found["pid"]))
        assert "serve" in serve.cmdline()
        os.kill(demo.pid, signal.SIGTERM)
        assert demo.wait(60) == 128 + signal.SIGTERM
        gone([serve], timeout=40)
        assert holder(data) is None
    finally:
        if demo.poll() is None:
            os.killpg(demo.pid, signal.SIGKILL)
        for child in psutil.process_iter(["cmdline"]):
            if str(data) in " ".join(child.info["cmdline"] or []):
                child.kill()


def test_labd_serve_runs_as_its_configuration_file_says(served, tmp_path):
    """A real lab takes its settings from --config, a LABD_ variable overriding the file:
    here sign-up on and no robots (the file), the playground kept (a variable over the file)."""
    config = tmp_path / "lab.toml"
    config.write_text(
        "[serve]\nsignup = true\nno_robots = true\nno_playground = true\nworkers = 0\n"
    )
    lab = served("--config", str(config), env={"LABD_NO_PLAYGROUND": "0"}).start()
    assert f"settings from {config}" in lab.log
    assert "robot " not in lab.log and "playground (no robot" in lab.log
    assert httpx.get(f"{lab.server}/signup", timeout=30).status_code == 200
    status = httpx.get(f"{lab.server}/api/status", timeout=30).json()
    assert status["local_workers"] == 0
