"""A lab whose environment names an HTTP proxy (``HTTP_PROXY`` and the rest, as a
company's machines have) reaches itself directly: its worker processes call its API, and
the lab and they fetch its hosted repositories, without a word to the proxy, which could
not reach this machine's loopback anyway."""

from __future__ import annotations

import socketserver
import threading
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from tests.faults.conftest import Served, wait_for
from tests.helpers.labs import shared_cache
from tests.integration.test_remote_playground import SHORT

pytestmark = [pytest.mark.integration, pytest.mark.timeout(300)]


class Proxy(socketserver.ThreadingTCPServer):
    """A listener where a proxy would be: it keeps the first bytes of each connection
    and answers 502, so a client that comes here fails at once and is seen."""

    daemon_threads = True
    allow_reuse_address = True

    def __init__(self) -> None:
        super().__init__(("127.0.0.1", 0), _Handler)
        self.seen: list[bytes] = []
        self.url = f"http://127.0.0.1:{self.server_address[1]}"


class _Handler(socketserver.StreamRequestHandler):
    server: Proxy

    def handle(self) -> None:
        self.server.seen.append(self.request.recv(300))
        self.wfile.write(b"HTTP/1.1 502 Bad Gateway\r\nContent-Length: 0\r\n\r\n")


@pytest.fixture
def proxy() -> Iterator[Proxy]:
    server = Proxy()
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    yield server
    server.shutdown()
    server.server_close()


def test_the_labs_worker_processes_reach_it_past_the_environments_proxy(
    proxy: Proxy, cache: Path, tmp_path: Path
) -> None:
    """With every proxy variable set to a listener, a playground trial is committed,
    fetched, claimed, run by a worker process and filed, and the listener sees nothing."""
    variables = ("HTTP_PROXY", "HTTPS_PROXY", "ALL_PROXY")
    env = {name: proxy.url for upper in variables for name in (upper, upper.lower())}
    shared_cache(tmp_path / "lab", cache)
    lab = Served(
        tmp_path / "data",
        tmp_path / "lab" / "cache",
        "--no-robots", "--workers", "0", "--worker-processes", "1", "--sandbox", "bwrap",
        env=env,
    )  # fmt: skip
    lab.token = lab.add_user("alice")
    try:
        lab.start()
        body = {"name": "proxied", "task": "icreate-maze", "script": SHORT}
        made = httpx.post(
            f"{lab.server}/api/playground/trials",
            json=body,
            headers={"Authorization": f"Bearer {lab.token}"},
            timeout=120,
        )
        assert not proxy.seen, proxy.seen
        assert made.status_code == 201, made.text
        trial_id = made.json()["trial"]["id"]
        wait_for(
            "the trial to end, or a request at the proxy",
            lambda: proxy.seen or lab.trial(trial_id)["status"] == "finished",
            180,
            every=0.25,
            detail=lambda: lab.log[-3000:],
        )
        assert not proxy.seen, (proxy.seen, lab.log[-3000:])
        trial = lab.trial(trial_id)
    finally:
        lab.stop()
    assert trial["outcome"] == "fail" and "before the episode ended" in trial["reason"], trial
    assert trial["worker"].startswith("local-workers@"), trial["worker"]  # a worker process
