"""Slow conditions for the fault suite, real ones: no hook in the lab is needed.

- ``controller(ticks, pause)``: the files of a repository whose controller steps
  ``ticks`` times, ``pause`` seconds apart (with ``requirements=True`` it imports
  ``tinypkg``, which its requirements name);
- ``Held``: a repository whose controller steps until the test lets it go (a file the
  test writes into its checkout), so its trial runs for as long as a test needs it to;
- ``PackageIndex``: a PEP 503 index on 127.0.0.1 serving ``tinypkg``, whose page waits
  until the test sets ``release`` (a trial is held while preparing);
- ``S3Server``: moto's S3 server in a process of its own, which ``pause`` freezes with
  SIGSTOP (a trial is held while filing) and ``resume`` thaws.
"""

from __future__ import annotations

import base64
import contextlib
import hashlib
import io
import signal
import subprocess
import sys
import tempfile
import threading
import uuid
import zipfile
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any, ClassVar

import pytest
import s3fs

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
    """A repository whose controller steps ``ticks`` times, ``pause`` s apart, then exits;
    with ``requirements``, it needs tinypkg, installed afresh (never from the cache)."""
    toml = TOML.replace('"c.py"]', f'"c.py", "{ticks}", "{pause}"]')
    files = {"lab.toml": toml, "c.py": STEPS}
    if requirements:
        files["lab.toml"] += 'requirements = "requirements.txt"\n'
        # a line of its own makes the file new, so no earlier install is found in the cache
        files["requirements.txt"] = f"tinypkg==1.0  # {uuid.uuid4().hex}\n"
        files["c.py"] = "import tinypkg\nprint('tinypkg', tinypkg.VALUE)\n" + STEPS
    return files


HELD = """\
import os, time
from controllers.client import Lab
# held: {token}
with Lab.connect() as lab:
    while not os.path.exists("let-go"):  # written into the checkout by the test
        lab.publish("/cmd_vel", "geometry_msgs/msg/Twist", {{"angular": {{"z": 0.5}}}})
        lab.step()
        time.sleep(0.1)  # the pace of its steps: a small record
"""


class Held:
    """A repository whose controller steps, a tenth of a second apart, until ``let_go``:
    its trial (submitted with ``params``: an episode of an hour) runs until then.

    Run by a lab on this machine (its workers' checkouts are in the same temporary folder
    as the test's): ``let_go`` writes a file into the checkout, which the sandbox sees."""

    params: ClassVar[dict[str, float]] = {"time_limit": 3600.0}  # the episode outlasts a test

    def __init__(self) -> None:
        self.token = uuid.uuid4().hex
        self.files = {"lab.toml": TOML, "c.py": HELD.format(token=self.token)}

    def let_go(self) -> int:
        """Let every checkout of this controller go; how many there were."""
        let_go = 0
        for code in Path(tempfile.gettempdir()).glob("labd-trial-*/code/c.py"):
            with contextlib.suppress(FileNotFoundError):  # another trial's, just removed
                if self.token in code.read_text():
                    (code.parent / "let-go").write_text("")
                    let_go += 1
        return let_go


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
