"""Signing in through an OpenID provider in a real browser (Chromium).

The provider (``oidc-provider-mock``) listens on 127.0.0.1 and the browser reaches it
as ``localhost``: another site than the lab's 127.0.0.1, as a real provider is, so the
way back from it is a cross-site navigation, on which the browser withholds the lab's
SameSite=Strict cookies. The person clicks "Sign in with ..." on the sign-in page,
answers the provider's page, and lands signed in on the page they came for.
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
import werkzeug.serving

from labd.oidc import OidcConfig, Provider
from tests.helpers.labs import lab_config, running
from tests.integration.browser import Watched, browser, watched

__all__ = ["browser", "watched"]  # the module's fixtures

oidc_provider_mock = pytest.importorskip("oidc_provider_mock")

pytestmark = [pytest.mark.integration, pytest.mark.timeout(180)]


@contextlib.contextmanager
def provider_on_localhost() -> Iterator[str]:
    server = werkzeug.serving.make_server("127.0.0.1", 0, oidc_provider_mock.app(), threaded=True)
    thread = threading.Thread(target=server.serve_forever, args=(0.05,), daemon=True)
    thread.start()
    try:
        yield f"http://localhost:{server.server_port}"
    finally:
        server.shutdown()
        thread.join(10)
        server.server_close()


@pytest.fixture
def signin_server(tmp_path: Path) -> Iterator[tuple[Any, str]]:
    with provider_on_localhost() as issuer:
        config = OidcConfig((Provider("uni", issuer, "labd", "shh", "Test University"),))
        with running(lab_config(tmp_path / "data", robots=(), service={"oidc": config})) as server:
            yield server, issuer


def me(page: Any) -> Any:
    """``GET /api/me`` from the page, with its cookies."""
    return page.evaluate(
        "async () => { const r = await fetch('/api/me'); return [r.status, await r.json()]; }"
    )


PICO = "https://cdn.jsdelivr.net/npm/@picocss/pico@2/css/pico.min.css"


def provider_page_allowed(seen: Watched) -> None:
    """The provider's own page asks a CDN for its style sheet (nothing leaves this
    machine: the request is aborted); that is the provider's, not the lab's."""
    seen.outside = [url for url in seen.outside if url != PICO]
    seen.expected.add(f"failed {PICO}: net::ERR_FAILED")


def sign_in(page: Any, server: Any, subject: str) -> None:
    page.goto(server.http_url("/session?then=/tokens"))
    page.click("#oidc-uni")
    page.wait_for_url("**/oauth2/authorize**")
    page.fill("input[name=sub]", subject)
    page.click("button:has-text('Authorize')")
    page.wait_for_url(server.http_url("/tokens"))


def test_a_person_signs_in_in_a_browser_and_again_to_the_same_account(
    signin_server: tuple[Any, str], watched: Watched, browser: Any
) -> None:
    """Through the whole redirect flow in Chromium: the lab's session works at once on
    the page they land on (its name in the header, /api/me answering), and a second
    sign-in, in a fresh browser, reaches the same account."""
    server, issuer = signin_server
    httpx.put(
        f"{issuer}/users/s-ann",
        json={"email": "ann@example.edu", "email_verified": True, "preferred_username": "ann"},
        timeout=10,
    ).raise_for_status()
    page = watched.page
    sign_in(page, server, "s-ann")
    assert page.locator("h1").first.inner_text() == "Your API tokens"
    assert "ann" in page.locator("header").inner_text()
    status, body = me(page)
    assert (status, body["name"]) == (200, "ann")
    provider_page_allowed(watched)
    watched.check()

    fresh = browser.new_context()
    try:
        other = fresh.new_page()
        sign_in(other, server, "s-ann")
        status, body = me(other)
        assert (status, body["name"]) == (200, "ann")
    finally:
        fresh.close()


def test_a_forged_state_in_a_browser_signs_nobody_in(
    signin_server: tuple[Any, str], watched: Watched
) -> None:
    server, _ = signin_server
    page = watched.page
    page.goto(server.http_url("/session/oidc?then=/tokens"))  # a flow of this browser's
    page.wait_for_url("**/oauth2/authorize**")
    forged = server.http_url("/session/oidc/callback?code=stolen&state=forged")
    watched.expected.add(f"403 {forged}")
    page.goto(forged)
    assert page.locator("#refused h1").inner_text() == "Nobody was signed in"
    assert "state" in page.locator("#problem").inner_text()
    status, _ = me(page)
    assert status == 401
    watched.expected.add(f"401 {server.http_url('/api/me')}")
    provider_page_allowed(watched)
    watched.check()
