"""The live robots' pages in a real browser, against a real lab with both robots.

The iCreate page drives the robot (a key held, /odom moves) and shows camera frames in
interface A and the tags in B; a watcher's commands are refused with a status the page
shows; a page in a background tab stops the camera; the interface is drawn at random per
session and recorded; the PR2 page draws the robot in 3D and a Cartesian target moves
its arm; after a drive, the demonstration is in the archive with the page's events.
Screenshots go to build/screenshots/.
"""

from __future__ import annotations

import json
import re
import time

import httpx
import pytest
import roslibpy

from labd.config import DriveLimits
from labd.graph.types import TypeRegistry
from labd.recorder import read_messages
from repository.index import Filters
from repository.trial import Kind
from tests.helpers.labs import MAZE, PR2, ServerThread, lab_config, running
from tests.helpers.timing import SECOND
from tests.integration.browser import browser, watched
from tests.integration.test_browser import shot

__all__ = ["browser", "watched"]
pytestmark = [pytest.mark.integration, pytest.mark.timeout(300 * SECOND)]
CAMERA = "/camera/image/compressed"
MIN_TICKS = DriveLimits().min_ticks
# The drive's own episode (its seed, from /lab/driver) has run long enough to be filed.
LONG_ENOUGH = (
    "window.labLive.episode.seed === Number(document.body.dataset.seed)"
    f" && window.labLive.episode.tick >= {MIN_TICKS}"
)


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    """One lab for the module: icreate-1 and pr2-1 live, the archive, no workers."""
    data = tmp_path_factory.mktemp("live") / "data"
    with running(lab_config(data, (MAZE, PR2), interface_seed=7)) as server:
        yield server


def hold(page, key: str, until: str, timeout: float = 30) -> None:
    """Hold ``key`` down until the page's condition ``until`` holds."""
    page.keyboard.down(key)
    try:
        page.wait_for_function(until, timeout=timeout * 1000)
    finally:
        page.keyboard.up(key)


def camera_watchers(server: ServerThread) -> int:
    """The clients subscribed to the maze robot's camera (on the lab's loop)."""
    graph = server.lab.graphs["icreate-1"]
    return len(graph.subscribers_of(CAMERA))


def ux_events(server: ServerThread, demo, tmp_path) -> list:
    """The page's events in a demonstration's record."""
    record = tmp_path / f"{demo.id}.mcap"
    server.lab.service.store.copy_to(demo.mcap, record)
    types = TypeRegistry.default().typestore
    return [
        types.deserialize_cdr(m.data, "lab_msgs/msg/UxEvent")
        for m in read_messages(record, topics=["/ux/events"])
    ]


# The kinds of the user-experience events the page sends, in window.uxSent, from now on.
SENT = """() => {
  const live = window.labLive, send = live.ux;
  window.uxSent = [];
  live.ux = (kind, ...rest) => { window.uxSent.push(kind); return send(kind, ...rest); };
}"""


def test_the_icreate_page_drives_and_files_a_demonstration(server, watched, tmp_path):
    """Interface A shows camera frames; a held key drives (/odom moves); while another
    client drives, the page shows who, and its key press is refused with a status it
    shows; a background tab stops the camera; released, the drive is a demonstration in
    the archive with its interface and the page's events (key presses, clicks, the
    interface, focus, latency)."""
    page = watched.page
    page.goto(server.http_url("/robots/icreate-1?interface=video"))
    page.wait_for_function("Number(document.getElementById('camera').dataset.frames || 0) >= 3")
    page.click("#take")
    page.wait_for_function("document.body.dataset.driving === 'yes'")
    hold(page, "ArrowUp", "Number(document.getElementById('odom').dataset.x) > 0.1")
    page.wait_for_function(LONG_ENOUGH)
    page.evaluate("window.dispatchEvent(new Event('blur'))")  # the person looks elsewhere
    shot(watched, "live-icreate-video")

    page.click("#release")
    page.wait_for_function("document.body.dataset.driving === 'no'")

    # someone else drives (a roslibpy client): the page watches, and is refused
    other = roslibpy.Ros(host=server.url + "/robots/icreate-1")
    other.run(timeout=10)
    try:
        answer = roslibpy.Service(other, "/lab/drive", "lab_msgs/srv/Drive").call(
            roslibpy.ServiceRequest({"session": "s-2", "interface": "", "user": "bob"}), timeout=10
        )
        assert answer["success"], answer
        page.wait_for_function("document.getElementById('driver').textContent.includes('guest:')")
        page.keyboard.press("ArrowUp")
        page.wait_for_function(  # bob's drive is the lab's guest name's, not the one it typed
            "/driven by guest:client_\\d+; you are watching/"
            ".test(document.getElementById('status').textContent)"
        )
        assert page.get_attribute("#status", "data-level") in ("warning", "error")
        assert page.inner_text("#you").endswith("watching")
        listed = httpx.get(server.http_url("/robots")).text
        assert re.search(r'class="driver">guest:client_\d+', listed), listed
    finally:
        other.close()
    page.wait_for_function("document.getElementById('driver').textContent === 'nobody'")
    page.click("#take")
    page.wait_for_function("document.body.dataset.driving === 'yes'")
    page.evaluate(SENT)  # the events the page sends from now on, by kind
    page.keyboard.press("ArrowUp")  # a drive with no command at all is no demonstration
    page.wait_for_function("window.uxSent.includes('latency')")  # summed up every 2 s
    page.wait_for_function(LONG_ENOUGH)

    before = server.call(lambda: camera_watchers(server))
    assert before >= 1
    page.evaluate(
        """() => { Object.defineProperty(document, 'visibilityState', {value: 'hidden', configurable: true});
                   document.dispatchEvent(new Event('visibilitychange')); }"""
    )
    server.wait_until(lambda: camera_watchers(server) == before - 1)
    page.click("#release")
    page.wait_for_function("document.body.dataset.driving === 'no'")
    watched.check()

    service = server.lab.service
    deadline = time.monotonic() + 30 * SECOND
    while len(found := service.index.find(Filters(kind=Kind.DEMONSTRATION)).items) < 2:
        assert time.monotonic() < deadline, f"{len(found)} demonstrations filed, not 2"
        time.sleep(0.1)
    # the page's two drives; bob's gave no command, so it is no demonstration
    mine = [d for d in found if d.manifest["driver"].get("claimed_user") == "guest"]
    assert len(mine) == len(found) == 2 and {d.task for d in found} == {"icreate-maze"}
    assert all(d.submitter.startswith("guest:client_") for d in mine)
    assert all(d.manifest["driver"]["interface"] == "video" for d in mine)
    events = [e for demo in mine for e in ux_events(server, demo, tmp_path)]
    kinds = {e.kind for e in events}
    assert {"interface", "key", "click", "focus", "latency"} <= kinds, kinds
    assert any(e.kind == "key" and e.key == "ArrowUp" for e in events)
    assert any(e.kind == "interface" and e.key == "video" for e in events)
    page.evaluate(
        "() => Object.defineProperty(document, 'visibilityState', {value: 'visible', configurable: true})"
    )
    page.goto(server.http_url(f"/trials/{mine[0].id}"))
    assert "video" in page.inner_text("dl.facts")
    page.wait_for_function("document.getElementById('ux-events') !== null", timeout=60_000)
    assert "latency" in page.inner_text("#ux-events summary")


def test_interface_b_shows_the_tags(server, watched):
    """Interface B draws no video: the tags the robot detects are drawn (turning in place
    until some are in view), with its odometry and the goal."""
    page = watched.page
    page.goto(server.http_url("/robots/icreate-1?interface=perception"))
    assert page.query_selector("#camera") is None
    page.wait_for_function("document.body.dataset.ready === 'yes'")
    page.wait_for_function("Number(document.getElementById('perception').dataset.frames || 0) > 2")
    page.click("#take")
    page.wait_for_function("document.body.dataset.driving === 'yes'")
    hold(page, "ArrowLeft", "Number(document.getElementById('perception').dataset.tags) > 0")
    page.wait_for_function("document.getElementById('goal').textContent.includes('m away')")
    shot(watched, "live-icreate-perception")
    page.click("#release")
    page.wait_for_function("document.body.dataset.driving === 'no'")
    watched.check()


# A gamepad the page polls through the Gamepad API: its left stick is pushed forward
# (axis 1 at -1) once the test sets window.padForward; "gamepadconnected" is sent by the test.
GAMEPAD = """
(() => {
  const pad = { id: "test pad (STANDARD GAMEPAD)", index: 0, connected: true, mapping: "standard",
                buttons: Array.from({ length: 17 }, () => ({ pressed: false, value: 0 })),
                get axes() { return [0, window.padForward ? -1 : 0, 0, 0]; } };
  navigator.getGamepads = () => [pad, null, null, null];
  window.connectPad = () => {
    const event = new Event("gamepadconnected");
    Object.defineProperty(event, "gamepad", { value: pad });
    window.dispatchEvent(event);
  };
})();
"""


ODOM = "() => ['x', 'y'].map((k) => Number(document.getElementById('odom').dataset[k]))"


def test_a_gamepad_drives(server, watched):
    """The left stick of a gamepad (the Gamepad API, polled) drives the robot forward,
    and letting it go stops it; the page names the pad and logs its connection."""
    page = watched.page
    page.add_init_script(GAMEPAD)
    page.goto(server.http_url("/robots/icreate-1?interface=perception"))
    page.wait_for_function("document.body.dataset.ready === 'yes'")
    page.evaluate("window.connectPad()")
    page.wait_for_function("document.getElementById('gamepad').textContent.includes('test pad')")
    page.click("#take")
    page.wait_for_function("document.body.dataset.driving === 'yes'")
    page.wait_for_function("document.getElementById('odom').dataset.y !== undefined")
    start = page.evaluate(ODOM)
    page.evaluate("window.padForward = true")
    page.wait_for_function(
        f"(() => {{ const [x, y] = ({ODOM})(); return Math.hypot(x - {start[0]}, y - {start[1]}) > 0.1; }})()"
    )
    page.evaluate("window.padForward = false")

    # stopped: odometry settles (two readings 20 of the robot's ticks apart agree)
    def still() -> bool:
        first, tick = page.evaluate(ODOM), page.evaluate("window.labLive.episode.tick")
        page.wait_for_function(  # or a new episode, from tick 0
            f"(t => t >= {tick + 20} || t < {tick})(window.labLive.episode.tick)"
        )
        return first == page.evaluate(ODOM)

    deadline = time.monotonic() + 20 * SECOND
    while not still():
        assert time.monotonic() < deadline, "the robot kept moving after the stick was let go"
    page.click("#release")
    page.wait_for_function("document.body.dataset.driving === 'no'")
    watched.check()


def test_the_interface_is_drawn_per_session(server):
    """Page loads without an override draw both interfaces (the lab's ratio); the
    override wins; an unknown one is refused; an unknown robot is a 404."""
    shown = []
    for _ in range(16):
        page = httpx.get(server.http_url("/robots/icreate-1")).text
        config = json.loads(re.search(r'id="live-config">(.*?)</script>', page, re.S)[1])
        assert config["assigned"] == "random"
        shown.append(config["interface"])
    assert set(shown) == {"video", "perception"}, shown
    assert httpx.get(server.http_url("/robots/icreate-1?interface=perception")).status_code == 200
    assert httpx.get(server.http_url("/robots/icreate-1?interface=radar")).status_code == 422
    assert httpx.get(server.http_url("/robots/nope")).status_code == 404
    listed = httpx.get(server.http_url("/api/robots")).json()
    assert [r["name"] for r in listed] == ["icreate-1", "pr2-1"]


def test_the_pr2_page_moves_an_arm_to_a_target(server, watched):
    """The PR2 page draws the robot and the table in 3D from the robot's topics; moving
    the left arm's Cartesian target with the keyboard moves the arm's tool frame."""
    page = watched.page
    page.goto(server.http_url("/robots/pr2-1"))
    page.wait_for_function("document.body.dataset.ready === 'yes'", timeout=60_000)
    page.wait_for_function(
        "Number(document.getElementById('pr2-scene')?.dataset.frames || 0) > 3", timeout=60_000
    )
    page.wait_for_function("window.labPr2 && window.labPr2.tool('left') !== null")
    assert page.evaluate("window.labPr2.bodyPose('torso_lift_link')") is not None
    page.wait_for_function("Number(document.getElementById('camera').dataset.frames || 0) >= 2")
    page.click("#take")
    page.wait_for_function("document.body.dataset.driving === 'yes'")
    # taking the robot starts an episode: its scene (and the targets) load anew first
    page.wait_for_function("window.labPr2.seed() === Number(document.body.dataset.seed)")
    page.wait_for_function("window.labPr2.tool('left') !== null")
    start = page.evaluate("window.labPr2.tool('left')")
    page.keyboard.press("1")
    for key in "uuuuuiiii":  # up 10 cm, forward 8 cm
        page.keyboard.press(key)
    target = page.evaluate("window.labPr2.target('left')")
    assert target[2] == pytest.approx(start[2] + 0.10, abs=0.03)
    page.wait_for_function(
        """([x, y, z]) => { const t = window.labPr2.tool('left');
                           return Math.hypot(t[0] - x, t[1] - y, t[2] - z) < 0.03; }""",
        arg=target,
        timeout=60_000,
    )
    shot(watched, "live-pr2-3d")
    page.click("#release")
    page.wait_for_function("document.body.dataset.driving === 'no'")
    watched.check()
