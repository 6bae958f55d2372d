"""TLS for the whole lab: one certificate (``--tls-cert``/``--tls-key``) serves the pages
and API at https:// with Secure cookies, the robots at wss://, and the lab's own worker
processes reach it over https:// too."""

from __future__ import annotations

import ssl
import subprocess
from pathlib import Path
from typing import Any

import httpx
import pytest
from websockets.sync.client import connect

from tests.faults.conftest import wait_for
from tests.faults.slow import controller
from tests.helpers.githttp import GitRepo


@pytest.fixture
def certificate(tmp_path: Path) -> tuple[Path, Path]:
    """A self-signed certificate for 127.0.0.1, as an operator makes one for a test lab."""
    cert, key = tmp_path / "cert.pem", tmp_path / "key.pem"
    subprocess.run(
        [
            "openssl",
            "req",
            "-x509",
            "-newkey",
            "ec",
            "-pkeyopt",
            "ec_paramgen_curve:prime256v1",
            "-nodes",
            "-keyout",
            str(key),
            "-out",
            str(cert),
            "-days",
            "1",
            "-subj",
            "/CN=127.0.0.1",
            "-addext",
            "subjectAltName=IP:127.0.0.1",
        ],
        check=True,
        capture_output=True,
    )
    return cert, key


def test_one_certificate_serves_pages_robots_and_workers_over_tls(served, certificate, tmp_path):
    cert, key = certificate
    lab = served(
        "--tls-cert",
        str(cert),
        "--tls-key",
        str(key),
        "--robot",
        "icreate-1=icreate-maze",
        "--workers",
        "0",
        "--worker-processes",
        "1",
        "--sandbox",
        "bwrap",
        "--allow-local-repos",
    )
    lab.token = lab.add_user("alice")
    lab.start()  # fmt: skip
    assert lab.server.startswith("https://") and lab.bridge.startswith("wss://")
    with httpx.Client(verify=ssl.create_default_context(cafile=str(cert))) as http:
        page = http.get(f"{lab.server}/session")
        assert page.status_code == 200
        cookies = page.headers.get_list("set-cookie")
        assert cookies and all("secure" in c.lower() for c in cookies), cookies
        assert http.get(f"{lab.server}/healthz").json()["status"] == "ok"

        # a trial, run by the worker process, which reached the lab over https://
        token = {"Authorization": f"Bearer {lab.token}"}
        repo = GitRepo.create(tmp_path / "repo", controller(3)).path
        body = {"repository": str(repo), "task": "icreate-maze"}
        trial = http.post(f"{lab.server}/api/trials", json=body, headers=token).json()

        def ended() -> dict[str, Any] | None:
            row: dict[str, Any] = http.get(f"{lab.server}/api/trials/{trial['id']}").json()
            return row if row["status"] == "finished" else None

        row = wait_for("the trial", ended, timeout=180, every=0.5)
        assert row["outcome"] in ("success", "fail"), row  # it ran (--workers 0: not in the lab)
    with pytest.raises(httpx.ConnectError):  # a client that does not trust it is refused
        httpx.get(f"{lab.server}/healthz")
    context = ssl.create_default_context(cafile=str(cert))
    with connect(f"{lab.bridge}/robots/icreate-1", ssl=context) as ws:
        ws.send('{"op": "call_service", "id": "v", "service": "/rosapi/get_ros_version"}')
        assert '"result": true' in ws.recv(timeout=10).replace('"result":true', '"result": true')
