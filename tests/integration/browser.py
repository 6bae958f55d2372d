"""A real browser for the pages' tests: Debian's Chromium, driven by Playwright.

Playwright never downloads a browser here: it is pointed at ``/usr/bin/chromium``
(``.ci/run`` installs it), started headless with the flags this machine needs. Each
page a test opens records its console errors and every request that would leave
127.0.0.1; ``Watched.check()`` fails the test if there was any.

The lab's pages forbid evaluating strings as JavaScript (their Content-Security-Policy,
``labd/web/headers.py``), and Playwright polls a ``wait_for_function`` expression with
``eval``; ``csp_safe`` makes a page's ``wait_for_function`` pass an expression as a
function instead (as ``() => (EXPRESSION)``), which the policy does not touch.
"""

from __future__ import annotations

import os
import re
import shutil
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import pytest
from playwright.sync_api import sync_playwright

CHROMIUM = os.environ.get("LABD_CHROMIUM", "/usr/bin/chromium")
FLAGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--use-angle=swiftshader",
    "--enable-unsafe-swiftshader",
]
LOCAL = {"127.0.0.1", "localhost"}
# a function's text (not an expression that calls one, such as "(() => x)()")
FUNCTION = re.compile(r"\s*(async\s+)?(function\b|\(\s*[\w\s,]*\)\s*=>|\w+\s*=>)")


@dataclass
class Watched:
    """A page and what it did that a test must not allow."""

    page: Any
    errors: list[str] = field(default_factory=list)  # console errors, uncaught exceptions
    failed: list[str] = field(default_factory=list)  # "STATUS URL" of requests that failed
    outside: list[str] = field(default_factory=list)  # requests to another host (aborted)
    expected: set[str] = field(default_factory=set)  # failures a test asked for

    def check(self) -> None:
        assert self.errors == [], self.errors
        assert [f for f in self.failed if f not in self.expected] == [], self.failed
        assert self.outside == [], self.outside


def csp_safe(page: Any) -> Any:
    """``page``, its ``wait_for_function`` taking expressions under a CSP (docstring)."""
    original = page.wait_for_function

    def wait_for_function(expression: str, *args: Any, **kwargs: Any) -> Any:
        if not FUNCTION.match(expression):
            expression = f"() => ({expression})"
        return original(expression, *args, **kwargs)

    page.wait_for_function = wait_for_function
    return page


def chromium_or_skip() -> str:
    if shutil.which(CHROMIUM) or Path(CHROMIUM).exists():
        return CHROMIUM
    if os.environ.get("CI"):
        pytest.fail(f"no Chromium at {CHROMIUM}: .ci/run installs Debian's chromium")
    pytest.skip(f"no Chromium at {CHROMIUM}")


def assets_or_skip() -> None:
    """The pages' scripts (labd/web/static/vendor) are built (``make setup`` builds them
    from npm): without them every page test would wait out its timeouts."""
    built = Path(__file__).resolve().parents[2] / "labd" / "web" / "static" / "vendor" / ".built"
    if built.exists():
        return
    message = f"the pages' scripts are not built ({built} is missing): run make setup"
    if os.environ.get("CI"):
        pytest.fail(message)
    pytest.skip(message)


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    """Chromium, for one test module: Playwright's sync API keeps an event loop running
    while it is open, which the asyncio tests of later modules must not find."""
    assets_or_skip()
    executable = chromium_or_skip()
    with sync_playwright() as playwright:
        launched = playwright.chromium.launch(executable_path=executable, args=FLAGS)
        yield launched
        launched.close()


@pytest.fixture
def watched(browser: Any, tmp_path: Path) -> Iterator[Watched]:
    """A fresh page whose console errors and outside requests are kept."""
    context = browser.new_context(viewport={"width": 1280, "height": 900})
    page = csp_safe(context.new_page())
    seen = Watched(page)

    def console(message: Any) -> None:
        # a failed load is kept with its URL below; the console says only that one failed
        if message.type == "error" and not message.text.startswith("Failed to load resource"):
            seen.errors.append(message.text)

    page.on("console", console)
    page.on("pageerror", lambda e: seen.errors.append(str(e)))

    def failed(request: Any) -> None:
        # a load cut short by the next navigation (net::ERR_ABORTED) is no failure
        if "ERR_ABORTED" not in (request.failure or ""):
            seen.failed.append(f"failed {request.url}: {request.failure}")

    page.on("requestfailed", failed)
    page.on(
        "response",
        lambda r: seen.failed.append(f"{r.status} {r.url}") if r.status >= 400 else None,
    )

    def request(route: Any) -> None:
        host = urlsplit(route.request.url).hostname or ""
        if route.request.url.startswith(("data:", "blob:")) or host in LOCAL:
            route.continue_()
        else:
            seen.outside.append(route.request.url)
            route.abort()

    page.route("**/*", request)
    yield seen
    context.close()
