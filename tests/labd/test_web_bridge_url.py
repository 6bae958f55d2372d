"""The live pages' bridge address: wss:// whenever the page came over https."""

from __future__ import annotations

from starlette.requests import Request

from labd.api.site import Site
from labd.web.robots import bridge_url


def _request(scheme: str, host: str = "lab.example.org") -> Request:
    return Request(
        {
            "type": "http",
            "scheme": scheme,
            "method": "GET",
            "path": "/robots/icreate-1",
            "query_string": b"",
            "server": (host, 443 if scheme == "https" else 80),
            "headers": [(b"host", host.encode())],
        }
    )


def test_a_plain_page_reaches_the_bridge_over_ws():
    """A lab without a certificate, read over http: ws:// at the bridge's port."""
    url = bridge_url(_request("http"), Site(bridge_port=9090), "icreate-1")
    assert url == "ws://lab.example.org:9090/robots/icreate-1"


def test_a_lab_with_its_own_certificate_is_reached_over_wss():
    """--tls-cert: the bridge speaks wss://, whatever the page's scheme."""
    url = bridge_url(_request("http"), Site(bridge_port=9090, bridge_tls=True), "pr2-1")
    assert url == "wss://lab.example.org:9090/robots/pr2-1"


def test_a_page_over_https_behind_a_proxy_gets_wss():
    """A TLS proxy in front of a lab without a certificate (the page's scheme is https, as
    X-Forwarded-Proto from a trusted proxy makes it): wss://, since a browser refuses
    ws:// from an https page."""
    url = bridge_url(_request("https"), Site(bridge_port=9090), "icreate-1")
    assert url == "wss://lab.example.org:9090/robots/icreate-1"
