"""The ``labd`` commands a newcomer meets, run as processes: outcomes as exit codes,
errors as one line (or one JSON object), never a traceback."""

from __future__ import annotations

import json
import os
import shutil
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from repository.index import SCHEMA_VERSION, connect
from repository.migrate import schema_of
from tests.helpers.labs import shared_cache
from tests.helpers.sandboxes import make_backend
from tests.repository.test_migrate import schema_1

pytestmark = [pytest.mark.integration, pytest.mark.timeout(300)]
ROOT = Path(__file__).resolve().parents[2]
MAZE = ROOT / "controllers" / "examples" / "icreate-maze"
RAISES = ROOT / "tests" / "scheduler" / "attacks" / "raises"


def labd(*args: str, env: dict[str, str] | None = None, timeout: float = 240):
    return subprocess.run(
        [sys.executable, "-m", "labd", *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        check=False,
        env={**os.environ, **(env or {})},
    )


@pytest.mark.parametrize(
    ("source", "params", "outcome", "code"),
    [
        (MAZE, [], "success", 0),
        (MAZE, ["--param", "time_limit=2"], "fail", 1),
        (RAISES, [], "error", 3),
    ],
    ids=["reaches-the-goal", "runs-out-of-time", "crashes"],
)
def test_labd_run_exits_by_outcome(cache, tmp_path, source, params, outcome, code):
    """labd run exits 0 only on success: 1 for a fail (a maze run out of time), 3 for an
    error (a crash), and --json says the same as the exit code."""
    make_backend("bwrap", cache)
    data = tmp_path / "data"
    shared_cache(data, cache)
    folder = tmp_path / "code"
    shutil.copytree(source, folder)
    folder.chmod(0o755)
    done = labd(
        "run", str(folder), "--task", "icreate-maze", "--sandbox", "bwrap", "--data", str(data),
        "--seed", "1", *params, "--json",
    )  # fmt: skip
    result = json.loads(done.stdout)
    assert (result["status"], result["outcome"], done.returncode) == ("finished", outcome, code), (
        result["reason"]
    )
    text = labd(
        "run", str(folder), "--task", "icreate-maze", "--sandbox", "bwrap", "--data", str(data),
        "--seed", "1", *params,
    )  # fmt: skip
    assert text.returncode == code
    assert text.stdout.startswith(f"trial {outcome.upper()}: "), text.stdout


@pytest.mark.parametrize(
    ("given", "said"),
    [
        (["--task", "icreate-maz"], "no task 'icreate-maz' (did you mean icreate-maze?)"),
        (["--param", "maze_sise=5"], "parameter maze_sise is not a parameter of this task"),
    ],
    ids=["task", "parameter"],
)
def test_labd_run_of_a_misspelt_task_or_parameter_is_a_usage_error(cache, tmp_path, given, said):
    """A misspelt task or parameter is one line (a JSON error under --json) naming what
    is there, and the usage error's exit code: no traceback, and not "fail"."""
    make_backend("bwrap", cache)
    data = tmp_path / "data"
    shared_cache(data, cache)
    for extra in ([], ["--json"]):
        done = labd("run", str(MAZE), "--sandbox", "bwrap", "--data", str(data), *given, *extra)
        assert done.returncode == 2, done.stderr
        assert "Traceback" not in done.stderr + done.stdout
        text = json.loads(done.stdout)["error"] if extra else done.stderr
        assert said in text, text


def test_errors_under_json_are_json_with_the_same_exit_code(tmp_path):
    """A command that cannot do its work prints {"error": ...} on stdout under --json,
    and one line on stderr without it; both exit 2 and show no traceback."""
    nowhere = f"http://127.0.0.1:{free_port()}"
    as_json = labd("trials", "--server", nowhere, "--json")
    assert as_json.returncode == 2
    error = json.loads(as_json.stdout)["error"]
    assert "cannot reach the lab at" in error and "--server" in error and "LABD_SERVER" in error
    plain = labd("trials", "--server", nowhere)
    assert plain.returncode == 2 and plain.stdout == ""
    assert plain.stderr.startswith("labd trials: cannot reach the lab")
    assert "Traceback" not in plain.stderr + as_json.stderr
    usage = labd("trials", "--limit", "many", "--json")
    assert usage.returncode == 2
    assert "invalid int value: 'many'" in json.loads(usage.stdout)["error"]
    worker = labd("worker", "--json", env={"LABD_TOKEN": ""})
    assert worker.returncode == 2 and "worker's token" in json.loads(worker.stdout)["error"]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_a_busy_port_is_one_line_naming_the_flag(tmp_path):
    """labd serve on a port in use stops with one line naming the port and the flag."""
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        bridge = labd(
            "serve", "--bridge-port", str(port), "--no-robots", "--no-service",
            "--data", str(tmp_path), timeout=60,
        )  # fmt: skip
        http = labd(
            "serve", "--bridge-port", "0", "--http-port", str(port), "--no-robots",
            "--workers", "0", "--data", str(tmp_path), timeout=60,
        )  # fmt: skip
    for done, flag in ((bridge, "--bridge-port"), (http, "--http-port")):
        assert done.returncode == 2
        lines = done.stderr.strip().splitlines()
        assert lines[-1] == (
            f"labd serve: port {port} on 127.0.0.1 is in use (by another labd, or another"
            f" program); choose another with {flag} PORT (0 picks a free one)"
        ), done.stderr
        assert "Traceback" not in done.stderr


@pytest.mark.parametrize(
    ("flags", "words"),
    [
        (["--no-robots", "--no-playground"], "leaves the bridge nothing to serve"),
        (["--robot", "a=icreate-maze", "--no-robots"], "contradict each other"),
        (["--robot", "a=no-such-task"], "robot a: "),
        (["--robot", "nothing"], "write NAME=VALUE"),
        (["--bridge-port", "ninety"], "invalid int value"),
    ],
)
def test_flags_that_make_no_sense_are_one_line(tmp_path, flags, words):
    """Contradictory or malformed options are refused in one line, never a traceback."""
    done = labd("serve", "--data", str(tmp_path), *flags, timeout=60)
    assert done.returncode == 2
    assert words in done.stderr and "Traceback" not in done.stderr, done.stderr


def test_an_old_archive_is_refused_until_migrated(tmp_path):
    """labd serve on an index of labd 0.1 says to run labd migrate; after it, it starts."""
    data = tmp_path / "data"
    data.mkdir()
    url = f"sqlite:///{data / 'index.sqlite'}"
    schema_1(url)
    refused = labd("serve", "--data", str(data), "--no-robots", "--workers", "0", timeout=60)
    assert refused.returncode == 2
    assert refused.stderr.strip().splitlines()[-1].endswith(f"labd migrate --data {data}")
    migrated = labd("migrate", "--data", str(data), "--json", timeout=60)
    assert migrated.returncode == 0, migrated.stderr
    assert json.loads(migrated.stdout)["changed"] == {
        "succeeded -> success": 1,
        "succeeded -> fail": 2,
        "failed -> error": 1,
    }
    engine = connect(url)
    assert schema_of(engine) == SCHEMA_VERSION
    engine.dispose()


def test_a_reader_that_goes_away_is_not_a_traceback(tmp_path):
    """`labd ... | head` ending early: labd stops quietly, with no traceback."""
    read, write = os.pipe()
    os.close(read)  # the reader has gone before labd writes a byte
    try:
        done = subprocess.run(
            [sys.executable, "-m", "labd", "migrate", "--data", str(tmp_path), "--json"],
            stdout=write,
            stderr=subprocess.PIPE,
            timeout=60,
            check=False,
        )
    finally:
        os.close(write)
    assert done.returncode == 1
    assert done.stderr == b"", done.stderr.decode()


def test_labd_run_with_requirements_on_docker_from_a_relative_data_folder(cache, tmp_path):
    """The default --data (./lab-data, relative) works on Docker with a requirements file:
    every path is made absolute before it reaches the engine."""
    make_backend("docker", cache)
    shared_cache(tmp_path / "lab-data", cache)
    robot = tmp_path / "robot"
    robot.mkdir()
    (robot / "lab.toml").write_text(
        '[controller]\ncommand = ["python", "c.py"]\ntask = "icreate-maze"\n'
        'requirements = "requirements.txt"\n'
    )
    (robot / "requirements.txt").write_text("six==1.17.0\n")
    (robot / "c.py").write_text(
        "import six\nfrom controllers.client import Lab\nprint('six', six.__version__)\n"
        "with Lab.connect() as lab:\n    lab.step()\n"
    )
    done = subprocess.run(
        [sys.executable, "-m", "labd", "run", "robot", "--sandbox", "docker", "--json"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=240,
        check=False,
    )
    result = json.loads(done.stdout)
    assert "exited with 0 at tick 1" in result["reason"], result["reason"]
    assert result["backend"] == "docker"
    assert Path(result["folder"]).is_relative_to(tmp_path / "lab-data")
    assert (Path(result["folder"]) / "controller.stdout.log").read_text() == "six 1.17.0\n"
