"""`labd serve` SIGKILLed in each stage of a trial: preparing, running, filing.

Each stage is held by a real slow condition, not a hook: a package index that does not
answer yet (preparing: installing the requirements), a controller that steps slowly
(running), an S3 server that is stopped (filing: uploading the record). The lab is
killed there, its sandboxes die with it, and a new `labd serve` on the same data folder
requeues the trial at once. Every submission then ends exactly once: the killed trial
on its second attempt, the one queued behind it on its first, no trial made or lost,
and each record downloads intact.
"""

from __future__ import annotations

import base64
import hashlib
import io
import signal
import subprocess
import sys
import threading
import zipfile
from collections.abc import Iterator
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any, ClassVar

import httpx
import pytest
import s3fs

from tests.faults.conftest import gone, wait_for
from tests.helpers.githttp import GitRepo

pytestmark = pytest.mark.integration

TOML = '[controller]\ncommand = ["python", "c.py"]\ntask = "icreate-maze"\n'
STEPS = """\
import sys, time
from controllers.client import Lab
ticks, pause = int(sys.argv[1]), float(sys.argv[2])
with Lab.connect() as lab:
    for _ in range(ticks):
        lab.publish("/cmd_vel", "geometry_msgs/msg/Twist", {"angular": {"z": 0.5}})
        lab.step()
        time.sleep(pause)
"""


def controller(ticks: int, pause: float = 0.0, *, requirements: bool = False) -> dict[str, str]:
    """A repository whose controller steps ``ticks`` times, ``pause`` s apart, then exits."""
    toml = TOML.replace('"c.py"]', f'"c.py", "{ticks}", "{pause}"]')
    files = {"lab.toml": toml, "c.py": STEPS}
    if requirements:
        files["lab.toml"] += 'requirements = "requirements.txt"\n'
        files["requirements.txt"] = "tinypkg==1.0\n"
        files["c.py"] = "import tinypkg\nprint('tinypkg', tinypkg.VALUE)\n" + STEPS
    return files


# -- a package index that answers when the test lets it ------------------------------------


def tiny_wheel() -> tuple[str, bytes]:
    """A pure-Python wheel, ``tinypkg`` 1.0, made here (no index outside the test)."""
    files = {
        "tinypkg.py": b"VALUE = 7\n",
        "tinypkg-1.0.dist-info/METADATA": b"Metadata-Version: 2.1\nName: tinypkg\nVersion: 1.0\n",
        "tinypkg-1.0.dist-info/WHEEL": (
            b"Wheel-Version: 1.0\nGenerator: labd-tests\nRoot-Is-Purelib: true\nTag: py3-none-any\n"
        ),
    }
    record = []
    for name, data in files.items():
        digest = base64.urlsafe_b64encode(hashlib.sha256(data).digest()).rstrip(b"=").decode()
        record.append(f"{name},sha256={digest},{len(data)}")
    record.append("tinypkg-1.0.dist-info/RECORD,,")
    files["tinypkg-1.0.dist-info/RECORD"] = ("\n".join(record) + "\n").encode()
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as wheel:
        for name, data in files.items():
            wheel.writestr(name, data)
    return "tinypkg-1.0-py3-none-any.whl", buffer.getvalue()


class PackageIndex(ThreadingHTTPServer):
    """A PEP 503 index on 127.0.0.1 whose page of tinypkg waits until ``release`` is set."""

    daemon_threads = True

    def __init__(self) -> None:
        super().__init__(("127.0.0.1", 0), _IndexHandler)
        self.wheel_name, self.wheel = tiny_wheel()
        self.asked = threading.Event()  # pip has asked for the package
        self.release = threading.Event()
        threading.Thread(target=self.serve_forever, daemon=True).start()

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.server_address[1]}/simple"

    def handle_error(self, request: Any, client_address: Any) -> None:
        pass  # a pip killed with its lab leaves a broken connection: expected here


class _IndexHandler(BaseHTTPRequestHandler):
    server: PackageIndex
    protocol_version: ClassVar[str] = "HTTP/1.0"

    def do_GET(self) -> None:
        index = self.server
        if self.path.rstrip("/") == "/simple/tinypkg":
            index.asked.set()
            if not index.release.wait(120):
                self.send_error(503)
                return
            sha = hashlib.sha256(index.wheel).hexdigest()
            body = f'<a href="/files/{index.wheel_name}#sha256={sha}">{index.wheel_name}</a>'
            self._send(body.encode(), "text/html")
        elif self.path == f"/files/{index.wheel_name}":
            self._send(index.wheel, "application/octet-stream")
        else:
            self.send_error(404)

    def _send(self, body: bytes, kind: str) -> None:
        self.send_response(200)
        self.send_header("Content-Type", kind)
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    def log_message(self, format: str, *args: object) -> None:
        pass


@pytest.fixture
def index() -> Iterator[PackageIndex]:
    server = PackageIndex()
    yield server
    server.release.set()
    server.shutdown()
    server.server_close()


# -- an S3 server that can be stopped ----------------------------------------------------------


class S3Server:
    """moto's S3 server in a process of its own, so SIGSTOP can freeze it."""

    def __init__(self) -> None:
        self.process = subprocess.Popen(
            [sys.executable, "-m", "moto.server", "-H", "127.0.0.1", "-p", "0"],
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
        assert self.process.stdout is not None
        for line in self.process.stdout:
            if "Running on http://" in line:
                self.url = line.split("Running on ", 1)[1].strip()
                break
        else:
            pytest.fail("moto's S3 server did not start")
        threading.Thread(target=self.process.stdout.read, daemon=True).start()
        self.fs = s3fs.S3FileSystem(endpoint_url=self.url, key="testing", secret="testing")
        self.fs.mkdir("lab-archive")

    def pause(self) -> None:
        self.process.send_signal(signal.SIGSTOP)

    def resume(self) -> None:
        self.process.send_signal(signal.SIGCONT)

    def close(self) -> None:
        self.resume()
        self.process.terminate()
        self.process.wait(10)
        assert self.process.stdout is not None
        self.process.stdout.close()


@pytest.fixture
def s3(monkeypatch: pytest.MonkeyPatch) -> Iterator[S3Server]:
    monkeypatch.setenv("AWS_ACCESS_KEY_ID", "testing")
    monkeypatch.setenv("AWS_SECRET_ACCESS_KEY", "testing")
    server = S3Server()
    yield server
    server.close()


# -- the scenario ----------------------------------------------------------------------------


def kill_and_restart(lab, trial_id: int, stage: str) -> None:
    """SIGKILL the lab while the trial is in ``stage``; its sandboxes die; start it again."""
    assert lab.stage(trial_id) == stage
    assert lab.trial(trial_id)["status"] == "running"
    gone(lab.kill())
    lab.start()
    assert f"requeued trials a killed labd left running: [{trial_id}]" in lab.log, lab.log


def check_ended_once(lab, submitted: list[int], target: dict, queued: dict) -> None:
    """No trial made or lost; the killed one ran twice, the queued one once; records intact."""
    listed = lab.get("/api/trials?limit=500")["trials"]
    assert sorted(t["id"] for t in listed) == sorted(submitted)
    assert (target["attempts"], queued["attempts"]) == (2, 1)
    for row in (target, queued):
        assert row["status"] == "finished", row
        record = httpx.get(f"{lab.server}/api/trials/{row['id']}/data.mcap", timeout=30)
        assert record.status_code == 200
        assert "sha256:" + hashlib.sha256(record.content).hexdigest() == row["mcap"]["digest"]


@pytest.mark.timeout(180)
def test_sigkill_while_preparing(served, index: PackageIndex, tmp_path: Path):
    """Killed while the requirements install (the index has not answered): the trial is
    requeued, installs on its second attempt, runs and is filed once."""
    lab = served("--no-robots", "--workers", "1", "--sandbox", "bwrap", "--lease", "3",
                 env={"PIP_INDEX_URL": index.url})  # fmt: skip
    lab.token = lab.add_user("alice")
    lab.start()
    target = lab.submit(GitRepo.create(tmp_path / "t", controller(3, requirements=True)).path)
    queued = lab.submit(GitRepo.create(tmp_path / "q", controller(3)).path)
    assert index.asked.wait(60), lab.log
    kill_and_restart(lab, target["id"], "preparing")
    index.release.set()
    rows = lab.wait_ended([target["id"], queued["id"]], 120)
    for row in rows:
        assert row["reason"].startswith("the controller exited with 0 at tick 3"), row["reason"]
    check_ended_once(lab, [target["id"], queued["id"]], *rows)
    stdout = httpx.get(rows[0]["logs"]["stdout"], timeout=30).text
    assert stdout == "tinypkg 7\n"


@pytest.mark.timeout(180)
def test_sigkill_while_running(served, tmp_path: Path):
    """Killed while the controller steps: the trial is requeued, runs again from the start
    and is filed once, with the same data as an uninterrupted run."""
    lab = served("--no-robots", "--workers", "1", "--sandbox", "bwrap", "--lease", "3")
    lab.token = lab.add_user("alice")
    lab.start()
    target = lab.submit(GitRepo.create(tmp_path / "t", controller(40, 0.1)).path)
    queued = lab.submit(GitRepo.create(tmp_path / "q", controller(3)).path)
    record = lab.data / "work" / f"trial-{target['id']}-1" / "trial.mcap"
    wait_for("the first attempt to record", record.exists, 60, every=0.05)
    kill_and_restart(lab, target["id"], "running")
    rows = lab.wait_ended([target["id"], queued["id"]], 120)
    assert rows[0]["reason"].startswith("the controller exited with 0 at tick 40"), rows[0]
    check_ended_once(lab, [target["id"], queued["id"]], *rows)
    again = lab.submit(Path(rows[0]["repository"]))  # the same trial, never interrupted
    [same] = lab.wait_ended([again["id"]], 120)
    assert same["data_digest"] == rows[0]["data_digest"]


@pytest.mark.timeout(180)
def test_sigkill_while_filing(served, s3: S3Server, tmp_path: Path):
    """Killed while the record uploads to a stopped S3 server: the trial is requeued, and
    once the store answers again it runs and is filed once; the bucket holds its record."""
    lab = served("--no-robots", "--workers", "1", "--sandbox", "bwrap", "--lease", "3",
                 "--blobs", "s3://lab-archive/records", "--blobs-option",
                 f"endpoint_url={s3.url}")  # fmt: skip
    lab.token = lab.add_user("alice")
    lab.start()
    s3.pause()  # nothing touches the store before filing
    target = lab.submit(GitRepo.create(tmp_path / "t", controller(3)).path)
    queued = lab.submit(GitRepo.create(tmp_path / "q", controller(5)).path)
    wait_for("the trial to be filing", lambda: lab.stage(target["id"]) == "filing", 60)
    kill_and_restart(lab, target["id"], "filing")
    s3.resume()
    rows = lab.wait_ended([target["id"], queued["id"]], 120)
    assert rows[0]["reason"].startswith("the controller exited with 0 at tick 3"), rows[0]
    assert rows[1]["reason"].startswith("the controller exited with 0 at tick 5"), rows[1]
    check_ended_once(lab, [target["id"], queued["id"]], *rows)
    s3.fs.invalidate_cache()
    for row in rows:
        digest = row["mcap"]["digest"]
        assert s3.fs.exists(f"lab-archive/records/sha256/{digest[7:9]}/{digest[7:]}")
