"""``labd run --data DIR`` where DIR lies under a folder only its owner may enter.

Home folders are often 0700; the sandbox's unprivileged uid cannot search them, yet the
runtime, the installed requirements and the backend's state all live in DIR. Both
backends must run the trial from there (issue 9, part 4).
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from tests.helpers.githttp import GitRepo
from tests.helpers.sandboxes import BACKENDS, make_backend

pytestmark = [pytest.mark.integration, pytest.mark.timeout(300)]

ROBOT = {
    "lab.toml": (
        '[controller]\ncommand = ["python", "controller.py"]\ntask = "icreate-maze"\n'
        'requirements = "requirements.txt"\n'
    ),
    "requirements.txt": "six==1.17.0\n",
    "controller.py": (
        "import six\n"
        "from controllers.client import Lab\n"
        "print('six', six.__version__)\n"
        "with Lab.connect() as lab:\n"
        "    lab.step()\n"
    ),
}


@pytest.mark.parametrize("name", BACKENDS)
def test_labd_run_with_its_data_under_a_private_folder(
    name: str, cache: Path, tmp_path: Path
) -> None:
    """The trial runs, requirements and all, with --data under a 0700 folder."""
    make_backend(name, cache)  # the runtime is built (or skip: no such backend here)
    home = tmp_path / "home"
    home.mkdir()
    home.chmod(0o700)
    data = home / "lab-data"
    (data / "cache").mkdir(parents=True)
    for runtime in cache.glob("runtime-*"):  # the session's runtime, not a cold build
        (data / "cache" / runtime.name).symlink_to(runtime)
    robot = GitRepo.create(home / "robot", ROBOT)
    command = [sys.executable, "-m", "labd", "run", str(robot.path), "--sandbox", name]
    done = subprocess.run(
        [*command, "--data", str(data), "--json"],
        capture_output=True,
        text=True,
        timeout=240,
        check=False,
    )
    assert done.stdout, done.stderr
    result = json.loads(done.stdout)
    assert "the controller exited with 0 at tick 1" in result["reason"], result["reason"]
    assert (result["status"], result["outcome"], done.returncode) == ("finished", "fail", 1)
    assert result["backend"] == name and result["manifest"]["controller"]["requirements_sha256"]
    folder = Path(result["folder"])
    assert folder.is_relative_to(data)
    assert (folder / "controller.stdout.log").read_text() == "six 1.17.0\n"
