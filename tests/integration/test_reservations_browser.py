"""Reservations in a real browser (Debian's Chromium), against a real lab with
``--reservations``: Alice signs in with her password, books a short slot on the
reservations page, opens a page that drives the robot with her slot's key (fetched
through the API with her session), drives, is warned and then disconnected when the
slot ends; meanwhile Bob, signed in too, can neither book her slot nor drive in it.

The lab's robot page (``/robots/NAME``) is another piece of work; until it exists, the
drive page here is a minimal one that the test adds to the lab's own app (same origin,
so its fetch carries the session cookie): what it does is what that page will do, with
plain WebSocket frames of the rosbridge protocol.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from argon2 import PasswordHasher
from fastapi.responses import HTMLResponse

from labd.config import BridgeConfig, RobotConfig
from labd.lab import LabConfig
from labd.service import ServiceConfig
from repository.accounts import Accounts
from repository.index import Filters
from repository.trial import Kind
from tests.conftest import ServerThread
from tests.integration.browser import FLAGS, Watched, browser, watched

__all__ = ["FLAGS", "browser", "watched"]
pytestmark = [pytest.mark.integration, pytest.mark.timeout(180)]
SHOTS = Path(__file__).resolve().parents[2] / "build" / "screenshots"
PASSWORD = "correct horse battery"
SLOT_MINUTES = 0.4  # 24 s: time to drive, to see Bob refused, and the warning
WARNING = 6.0  # seconds before the end (a minute in a real lab)

DRIVE_PAGE = """<!doctype html>
<html><head><meta charset="utf-8"><title>drive icreate-1</title></head>
<body>
<p id="state">starting</p><p id="driver"></p><ul id="statuses"></ul><p id="closed"></p>
<script>
const show = (id, text) => { document.getElementById(id).textContent = text; };
let timer = null;
async function main() {
  const answer = await fetch("/api/robots/icreate-1/key");
  const body = await answer.json();
  const key = answer.ok ? body.key : null;
  show("state", key ? "connecting with my slot's key" : "watching: " + body.error);
  const ws = new WebSocket(`ws://${location.hostname}:BRIDGE/robots/icreate-1`);
  ws.onopen = () => {
    if (key) ws.send(JSON.stringify({op: "auth", key}));
    ws.send(JSON.stringify({op: "set_level", level: "warning"}));
    ws.send(JSON.stringify({op: "subscribe", topic: "/lab/driver", type: "lab_msgs/msg/Driver"}));
    ws.send(JSON.stringify({op: "advertise", topic: "/cmd_vel", type: "geometry_msgs/msg/Twist"}));
    let sent = 0;
    timer = setInterval(() => {
      if (sent++ < 40) {
        ws.send(JSON.stringify({op: "publish", topic: "/cmd_vel", msg: {linear: {x: 0.1}}}));
      }
    }, 100);
  };
  ws.onmessage = (event) => {
    const frame = JSON.parse(event.data);
    if (frame.op === "status") {
      const item = document.createElement("li");
      item.className = frame.level;
      item.textContent = frame.msg;
      document.getElementById("statuses").append(item);
    }
    if (frame.op === "publish" && frame.topic === "/lab/driver") {
      show("driver", "driver: " + (frame.msg.driver || "nobody"));
    }
  };
  ws.onclose = (event) => {
    clearInterval(timer);
    show("closed", `closed ${event.code}: ${event.reason}`);
  };
}
main();
</script></body></html>
"""


@pytest.fixture
def lab(tmp_path):
    data = tmp_path / "data"
    config = LabConfig(
        data=data,
        bridge=BridgeConfig(port=0, expiry_warning=WARNING),
        robots=(RobotConfig("icreate-1", "icreate-maze"),),
        playground=False,
        http_port=0,
        service=ServiceConfig(data=data, workers=0),
        reservations=True,
    )
    server = ServerThread(config).start()
    service = server.lab.service
    service.accounts = Accounts(service.index, hasher=PasswordHasher(time_cost=1, memory_cost=1024))
    for name in ("alice", "bob"):
        service.index.add_user(name, token=False)
        service.accounts.set_password(name, PASSWORD)
    yield server
    server.stop()


def url(lab: ServerThread, path: str = "") -> str:
    assert lab.lab is not None and lab.lab.http is not None
    return lab.lab.http.url() + path


def serve_drive_page(lab: ServerThread) -> str:
    """The drive page, on the lab's origin (so its fetch carries the session cookie)."""
    app = lab.lab.app
    path = "/test/drive/icreate-1"
    if not any(getattr(r, "path", None) == path for r in app.routes):
        html = DRIVE_PAGE.replace("BRIDGE", str(lab.port))
        app.add_api_route(path, lambda: HTMLResponse(html), include_in_schema=False)
    return url(lab, path)


def sign_in(lab: ServerThread, page, name: str) -> None:
    page.goto(url(lab, "/session?then=/reservations"))
    page.fill("#name", name)
    page.fill("#password", PASSWORD)
    page.click("#password-signin button[type=submit]")
    page.wait_for_url("**/reservations")
    assert page.locator("#me").inner_text() == name


def shot(page, name: str) -> None:
    SHOTS.mkdir(parents=True, exist_ok=True)
    page.screenshot(path=str(SHOTS / f"{name}.png"), full_page=True)


def test_book_drive_be_warned_and_disconnected_while_another_cannot_drive(
    lab, watched: Watched, browser
):
    """Alice books a slot and drives in it, is warned before it ends and disconnected
    when it does; Bob can neither book her slot nor drive in it; her drive is filed
    under her name."""
    alice = watched.page
    sign_in(lab, alice, "alice")
    bob_context = browser.new_context()
    bob = bob_context.new_page()
    try:
        sign_in(lab, bob, "bob")

        alice.fill("#minutes", str(SLOT_MINUTES))
        alice.click("#book-form button[type=submit]")
        alice.wait_for_url("**/reservations?done=*")
        assert "Done: booked" in alice.locator("#done").inner_text()
        assert "alice" in alice.locator("#robot-icreate-1").inner_text()
        shot(alice, "reservations-booked")

        alice.goto(serve_drive_page(lab))
        alice.wait_for_function(
            "document.getElementById('driver').textContent === 'driver: alice'", timeout=15_000
        )
        drives = lab.lab.drives["icreate-1"]
        assert drives.current is not None and drives.current.user == "alice"

        # Bob, meanwhile: the slot is taken, and his page only watches.
        bob.goto(url(lab, "/reservations"))
        bob.fill("#minutes", "5")
        bob.click("#book-form button[type=submit]")
        assert "icreate-1 is booked from" in bob.locator("#problem").inner_text()
        assert "by alice" in bob.locator("#problem").inner_text()
        bob.goto(serve_drive_page(lab))
        bob.wait_for_function(
            "[...document.querySelectorAll('#statuses li')].some("
            "li => li.textContent.includes('driven only in a reserved slot'))",
            timeout=15_000,
        )
        assert "bob has no slot of icreate-1 now" in bob.locator("#state").inner_text()
        assert drives.current.user == "alice"
        shot(bob, "reservations-bob-watches")

        alice.wait_for_function(
            "[...document.querySelectorAll('#statuses li.warning')].some("
            "li => li.textContent.includes('the time of your key ends in'))",
            timeout=30_000,
        )
        assert alice.locator("#closed").inner_text() == ""  # warned, still connected
        shot(alice, "reservations-warned")
        alice.wait_for_function(
            "document.getElementById('closed').textContent !== ''", timeout=30_000
        )
        assert alice.locator("#closed").inner_text() == (
            "closed 1008: the authorization has expired"
        )
    finally:
        bob_context.close()
    lab.wait_until(lambda: drives.current is None)
    watched.expected.update(
        f for f in watched.failed if "/api/robots/icreate-1/key" in f and f.startswith("404")
    )
    watched.check()
    index = lab.lab.service.index
    lab.wait_until(lambda: bool(index.find(Filters(kind=Kind.DEMONSTRATION)).items), 30)
    assert [d.submitter for d in index.find(Filters(kind=Kind.DEMONSTRATION)).items] == ["alice"]
