"""Submissions as a port scanner (issue 32), on a real `labd serve`.

A submitter names a repository at ``https://127.0.0.1:PORT/...`` or
``git://127.0.0.1:PORT/...``; the lab's git connects there from the lab's own machine.
When git's error came back in the answer, its words told a closed port ("Couldn't
connect") from an HTTP one ("wrong version number", "bad line length"), a TLS one
("certificate problem") or the lab's own WebSocket bridge: the lab mapped its own
loopback for anyone with an account. Now:

- by default a host that is not public (loopback, link-local, private...) is refused
  before any connection, in words that name the setting that allows it;
- where the operator allows private hosts, every network failure is answered in the
  same words, and git's own go to the lab's log only.
"""

from __future__ import annotations

import contextlib
import http.server
import socket
import ssl
import threading
from collections.abc import Callable, Iterator

import httpx
import pytest
import trustme

from tests.faults.conftest import Served

pytestmark = pytest.mark.integration


class Listener:
    """A server on 127.0.0.1 that counts the connections it accepts: plain HTTP that
    answers 404 to everything, or the same behind TLS (a certificate git does not trust)."""

    def __init__(self, tls: ssl.SSLContext | None = None) -> None:
        self.accepted = 0
        outer = self

        class Server(http.server.ThreadingHTTPServer):
            daemon_threads = True

            def get_request(self) -> tuple[socket.socket, object]:
                request = super().get_request()
                outer.accepted += 1
                return request

        class Handler(http.server.BaseHTTPRequestHandler):
            def do_GET(self) -> None:
                self.send_error(404)

            do_POST = do_GET

            def log_message(self, format: str, *args: object) -> None:
                pass

        self.httpd = Server(("127.0.0.1", 0), Handler)
        if tls is not None:
            self.httpd.socket = tls.wrap_socket(self.httpd.socket, server_side=True)
        self.port = int(self.httpd.server_address[1])
        self.thread = threading.Thread(target=self.httpd.serve_forever, args=(0.05,), daemon=True)
        self.thread.start()

    def close(self) -> None:
        self.httpd.shutdown()
        self.httpd.server_close()
        self.thread.join()


@contextlib.contextmanager
def listeners() -> Iterator[dict[str, Listener]]:
    """An HTTP and a TLS listener on loopback, closed at the end."""
    authority = trustme.CA()
    tls = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
    authority.issue_cert("127.0.0.1", "localhost").configure_cert(tls)
    made = {"http": Listener(), "tls": Listener(tls)}
    try:
        yield made
    finally:
        for listener in made.values():
            listener.close()


def closed_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


def submit(lab: Served, repository: str) -> httpx.Response:
    return httpx.post(
        f"{lab.server}/api/trials",
        json={"repository": repository, "task": "icreate-maze"},
        headers={"Authorization": f"Bearer {lab.token}"},
        timeout=120,
    )


def probes(ports: dict[str, int]) -> dict[tuple[str, str], str]:
    """For each port, a repository URL of each scheme the lab accepts by default."""
    return {
        (name, scheme): f"{scheme}://127.0.0.1:{port}/robot.git"
        for name, port in ports.items()
        for scheme in ("https", "git")
    }


def answered(ports: dict[str, int]) -> dict[tuple[str, str], str]:
    """The probes a server answers at once. An HTTP server waits for the end of a line
    that git's own protocol never sends, so a git:// URL to it ends at the fetch's time
    limit: the submitter's clock tells that apart whatever the words say, as it tells
    a silent server from a closed port; the words can only add what the clock does not."""
    return {probe: url for probe, url in probes(ports).items() if probe != ("http", "git")}


def test_failed_fetches_tell_no_port_from_another(make_bare_lab: Callable[..., Served]) -> None:
    """With private hosts allowed, a submission to a closed port, an HTTP one, a TLS one
    and the lab's own WebSocket bridge gets the same answer (its URL aside), over https
    and git alike; git's own words are in the lab's log, not in the answers."""
    allowed = {"LABD_ALLOW_PRIVATE_HOSTS": "1", "LABD_LOG_LEVEL": "INFO"}
    served = make_bare_lab("--resolve-timeout", "20", env=allowed)
    with listeners() as running:
        ports = {
            "closed": closed_port(),
            "http": running["http"].port,
            "tls": running["tls"].port,
            "websocket": int(served.bridge.rsplit(":", 1)[1]),
        }
        answers = {probe: submit(served, url) for probe, url in answered(ports).items()}
    said = {}
    for (name, scheme), answer in answers.items():
        assert answer.status_code == 422, (name, scheme, answer.text)
        url = f"{scheme}://127.0.0.1:{ports[name]}/robot.git"
        said[name, scheme] = answer.json()["error"].replace(url, "URL")
    assert len(set(said.values())) == 1, "\n".join(f"{k}: {v}" for k, v in said.items())
    assert "the repository could not be fetched" in next(iter(said.values()))
    # git's own words, which told the ports apart, are the operator's to read
    assert f"127.0.0.1:{ports['tls']}/robot.git could not be fetched: " in served.log
    assert "certificate" in served.log, served.log


def test_private_hosts_are_refused_before_any_connection(
    make_bare_lab: Callable[..., Served],
) -> None:
    """By default every loopback URL, by address or by name, is refused naming the
    setting that allows it, and nothing connects to the listeners it names; the lab's
    own hosted repositories (the playground's, on its loopback HTTP port) are fetched."""
    served = make_bare_lab()
    with listeners() as running:
        ports = {name: listener.port for name, listener in running.items()}
        urls = [*probes(ports).values(), f"https://localhost:{ports['tls']}/robot.git"]
        for url in urls:
            answer = submit(served, url)
            assert answer.status_code == 422, (url, answer.text)
            error = answer.json()["error"]
            assert "loopback address" in error and "--allow-private-hosts" in error, error
        assert {name: listener.accepted for name, listener in running.items()} == {
            "http": 0,
            "tls": 0,
        }
    assert served.get("/api/trials")["trials"] == []
    # the lab's own repositories, at its loopback address too, are fetched all the same
    script = {"name": "wanderer", "task": "icreate-maze", "script": "1;\n"}
    made = httpx.post(
        f"{served.server}/api/playground/trials",
        json=script,
        headers={"Authorization": f"Bearer {served.token}"},
        timeout=120,
    )
    assert made.status_code == 201, made.text
    assert made.json()["trial"]["repository"] == f"{served.server}/git/mallory/wanderer.git"
