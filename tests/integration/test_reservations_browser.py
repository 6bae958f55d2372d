"""Reservations in a real browser (Debian's Chromium), against a real lab with
``--reservations``: Alice signs in with her password, books a short slot on the
reservations page, opens the robot's page (``/robots/icreate-1``), which connects with
her slot's key (fetched through the API with her session), takes control and drives, is
warned and then disconnected when the slot ends; meanwhile Bob, signed in too, can
neither book her slot nor drive in it: his robot page only watches.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from argon2 import PasswordHasher

from labd.config import BridgeConfig
from repository.accounts import Accounts
from repository.index import Filters
from repository.trial import Kind
from tests.helpers.labs import ServerThread, lab_config, running
from tests.integration.browser import FLAGS, Watched, browser, csp_safe, watched

__all__ = ["FLAGS", "browser", "watched"]
pytestmark = [pytest.mark.integration, pytest.mark.timeout(180)]
SHOTS = Path(__file__).resolve().parents[2] / "build" / "screenshots"
PASSWORD = "correct horse battery"
SLOT_MINUTES = 0.4  # 24 s: time to drive, to see Bob refused, and the warning
WARNING = 6.0  # seconds before the end (a minute in a real lab)


@pytest.fixture
def server(tmp_path):
    bridge = BridgeConfig(port=0, expiry_warning=WARNING)
    with running(lab_config(tmp_path / "data", bridge=bridge, reservations=True)) as server:
        service = server.lab.service
        hasher = PasswordHasher(time_cost=1, memory_cost=1024)
        service.accounts = Accounts(service.index, hasher=hasher)
        for name in ("alice", "bob"):
            service.index.add_user(name, token=False)
            service.accounts.set_password(name, PASSWORD)
        yield server


def sign_in(server: ServerThread, page, name: str) -> None:
    page.goto(server.http_url("/session?then=/reservations"))
    page.fill("#name", name)
    page.fill("#password", PASSWORD)
    page.click("#password-signin button[type=submit]")
    page.wait_for_url("**/reservations")
    assert page.locator("#me").inner_text() == name


def shot(page, name: str) -> None:
    SHOTS.mkdir(parents=True, exist_ok=True)
    page.screenshot(path=str(SHOTS / f"{name}.png"), full_page=True)


def test_book_drive_be_warned_and_disconnected_while_another_cannot_drive(
    server, watched: Watched, browser
):
    """Alice books a slot and drives in it, is warned before it ends and disconnected
    when it does; Bob can neither book her slot nor drive in it; her drive is filed
    under her name."""
    alice = watched.page
    sign_in(server, alice, "alice")
    bob_context = browser.new_context()
    bob = csp_safe(bob_context.new_page())
    try:
        sign_in(server, bob, "bob")

        alice.fill("#minutes", str(SLOT_MINUTES))
        alice.click("#book-form button[type=submit]")
        alice.wait_for_url("**/reservations?done=*")
        assert "Done: booked" in alice.locator("#done").inner_text()
        assert "alice" in alice.locator("#robot-icreate-1").inner_text()
        shot(alice, "reservations-booked")

        robot = server.http_url("/robots/icreate-1?interface=perception")
        alice.goto(robot)
        alice.wait_for_function("document.body.dataset.ready === 'yes'", timeout=15_000)
        assert "connected with your slot's key" in alice.locator("#status").inner_text()
        alice.click("#take")
        alice.wait_for_function("document.body.dataset.driving === 'yes'", timeout=15_000)
        alice.wait_for_function("document.getElementById('driver').textContent.includes('alice')")
        alice.keyboard.down("ArrowUp")
        try:
            alice.wait_for_function(
                "Math.abs(Number(document.getElementById('odom').dataset.x)) > 0.05"
            )
        finally:
            alice.keyboard.up("ArrowUp")
        drives = server.lab.drives["icreate-1"]
        assert drives.current is not None and drives.current.user == "alice"

        # Bob, meanwhile: the slot is taken, and his robot page only watches.
        bob.goto(server.http_url("/reservations"))
        bob.fill("#minutes", "5")
        bob.click("#book-form button[type=submit]")
        assert "icreate-1 is booked from" in bob.locator("#problem").inner_text()
        assert "by alice" in bob.locator("#problem").inner_text()
        bob.goto(robot)
        bob.wait_for_function("document.body.dataset.ready === 'yes'", timeout=15_000)
        assert "watching (driving needs a slot's key)" in bob.locator("#status").inner_text()
        bob.wait_for_function("document.getElementById('driver').textContent.includes('alice')")
        bob.click("#take")
        bob.wait_for_function(
            "document.getElementById('status').dataset.level !== 'info'", timeout=15_000
        )
        refused = bob.locator("#status").inner_text()
        assert "driven only in a reserved slot; you are watching" in refused, refused
        assert bob.evaluate("document.body.dataset.driving") != "yes"
        assert drives.current.user == "alice"
        shot(bob, "reservations-bob-watches")

        alice.wait_for_function(
            "document.getElementById('status').textContent.includes('the time of your key ends in')",
            timeout=30_000,
        )
        shot(alice, "reservations-warned")
        alice.wait_for_function(
            "document.getElementById('status').textContent.includes('closed the connection')",
            timeout=30_000,
        )
    finally:
        bob_context.close()
    server.wait_until(lambda: drives.current is None)
    watched.expected.update(
        f for f in watched.failed if "/api/robots/icreate-1/key" in f and f.startswith("404")
    )
    watched.check()
    index = server.lab.service.index
    server.wait_until(lambda: bool(index.find(Filters(kind=Kind.DEMONSTRATION)).items), 30)
    assert [d.submitter for d in index.find(Filters(kind=Kind.DEMONSTRATION)).items] == ["alice"]
