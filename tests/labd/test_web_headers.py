"""The headers of the lab's answers in process: every page's Content-Security-Policy and
its nonce, nosniff and the referrer policy everywhere, and templates that need nothing
the policy forbids. (tests/integration/test_page_headers.py checks the pages in Chromium.)"""

from __future__ import annotations

import re

import httpx
import pytest

from labd.service import Service, ServiceConfig
from labd.web import RobotLink, Site, create_app
from labd.web.render import HERE

INLINE_SCRIPT = re.compile(r"<script(?![^>]*\bsrc=)(?![^>]*application/json)([^>]*)>", re.I)


@pytest.fixture
async def web(tmp_path):
    service = Service(ServiceConfig(data=tmp_path / "data", workers=0))
    site = Site((RobotLink("icreate-1", "icreate-maze", True),), bridge_port=9999)
    app = create_app(service, site, on_submit=lambda: None)
    transport = httpx.ASGITransport(app=app)
    async with httpx.AsyncClient(transport=transport, base_url="http://127.0.0.1:8080") as client:
        yield client
    service.index.close()


@pytest.mark.parametrize("path", ["/", "/robots/icreate-1", "/docs", "/redoc", "/session"])
async def test_a_page_carries_a_strict_policy_and_its_inline_scripts_its_nonce(web, path):
    """A page's policy allows scripts and styles from the lab and by this answer's nonce
    only, connections to the lab and its bridge's port, framing by nobody; every inline
    script of the page carries that nonce."""
    answer = await web.get(path)
    assert answer.status_code == 200
    policy = dict(
        part.strip().split(" ", 1) for part in answer.headers["content-security-policy"].split(";")
    )
    nonce = re.search(r"'nonce-([^']+)'", policy["script-src"]).group(1)
    assert policy["default-src"] == "'self'"
    assert policy["script-src"] == f"'self' 'nonce-{nonce}' 'wasm-unsafe-eval'"
    assert policy["style-src"] == f"'self' 'nonce-{nonce}'"
    assert policy["connect-src"] == "'self' ws://127.0.0.1:9999 wss://127.0.0.1:9999"
    assert policy["frame-ancestors"] == "'none'" and policy["object-src"] == "'none'"
    assert answer.headers["x-frame-options"] == "DENY"
    assert answer.headers["x-content-type-options"] == "nosniff"
    assert answer.headers["referrer-policy"] == "same-origin"
    for attributes in INLINE_SCRIPT.findall(answer.text):
        assert f'nonce="{nonce}"' in attributes, attributes
    assert (await web.get(path)).headers["content-security-policy"] != answer.headers[
        "content-security-policy"
    ], "a nonce is made for each answer"


@pytest.mark.parametrize("path", ["/api/trials", "/api/nothing", "/openapi.json"])
async def test_an_api_answer_runs_nothing_in_a_browser(web, path):
    """JSON (and an error) is served with nosniff and a policy that allows nothing."""
    answer = await web.get(path)
    assert answer.headers["content-security-policy"] == "default-src 'none'; frame-ancestors 'none'"
    assert answer.headers["x-content-type-options"] == "nosniff"
    assert answer.headers["referrer-policy"] == "same-origin"


async def test_a_static_file_is_nosniff(web):
    """A script or style of the pages is served with nosniff (and no policy of its own)."""
    answer = await web.get("/static/style.css")
    assert answer.headers["x-content-type-options"] == "nosniff"
    assert "content-security-policy" not in answer.headers


def test_no_template_needs_what_the_policy_forbids():
    """No template has an inline style attribute, an event handler attribute, a
    javascript: link, or an inline script or style without the nonce."""
    for template in sorted((HERE / "templates").glob("*.html")):
        text = template.read_text()
        assert not re.search(r"\sstyle=", text), template.name
        assert not re.search(r"\son[a-z]+=", text), template.name
        assert "javascript:" not in text, template.name
        for attributes in INLINE_SCRIPT.findall(text):
            assert 'nonce="{{ csp_nonce }}"' in attributes, (template.name, attributes)
        for attributes in re.findall(r"<style([^>]*)>", text):
            assert 'nonce="{{ csp_nonce }}"' in attributes, (template.name, attributes)
