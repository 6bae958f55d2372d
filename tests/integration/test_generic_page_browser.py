"""The generic live page in a real browser, for a task without a page of its own (a
dm_control suite task): its camera, its model in 3D, a slider per action dimension that
drives the robot through the bridge, and rolling plots of its observations."""

from __future__ import annotations

import pytest

from labd.config import RobotConfig
from tests.helpers.labs import lab_config, running
from tests.integration.browser import browser, watched
from tests.integration.test_browser import shot

__all__ = ["browser", "watched"]
pytestmark = [pytest.mark.integration, pytest.mark.timeout(180)]
CART = RobotConfig("cart-1", "dmc-cartpole-swingup")


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    """One lab for the module: the cart-pole swing-up live (cart-1), the archive."""
    with running(lab_config(tmp_path_factory.mktemp("generic") / "data", (CART,))) as server:
        yield server


def test_sliders_drive_a_suite_task_and_its_observations_are_plotted(server, watched):
    """Moving the cart's slider takes control and pushes the cart along its rail; the
    camera shows frames, the model is drawn and posed, and /observation/position and
    /reward are plotted as they come."""
    robot = server.lab.robots["cart-1"]
    page = watched.page
    page.goto(server.http_url("/robots/cart-1"))
    page.wait_for_function("document.body.dataset.ready === 'yes'", timeout=30_000)
    assert page.locator("#sliders input[type=range]").count() == 1  # cartpole: one actuator
    assert page.locator("label[for=action-0]").inner_text() == "slide"  # its actuator
    start = server.call(lambda: float(robot.sim.physics.data.qpos[0]))
    page.locator("#action-0").fill("1")
    page.wait_for_function("document.body.dataset.driving === 'yes'", timeout=20_000)
    server.wait_until(lambda: float(robot.sim.physics.data.qpos[0]) > start + 0.2, timeout=20)
    page.wait_for_function("Number(document.getElementById('camera').dataset.frames || 0) > 2")
    page.wait_for_function("Number(document.getElementById('scene3d').dataset.posed || 0) > 2")
    for topic in ("_observation_position", "_reward"):
        page.wait_for_function(
            f"Number(document.getElementById('plot-{topic}').dataset.points || 0) > 5"
        )
    shot(watched, "generic-live-page")
    page.click("#neutral")
    page.click("#release")
    server.wait_until(lambda: server.lab.drives["cart-1"].current is None, timeout=20)
    watched.check()
