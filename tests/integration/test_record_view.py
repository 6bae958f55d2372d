"""The look inside a record, on a trial's page, in a real browser against a real lab.

Trials made through the pages by a lab with a worker on bubblewrap: a maze controller
that watches the camera, and a PR2 controller that moves an arm. Each page draws its
plots, the maze's its camera frames and its map with the path, both the 3D scene; the
scrubber moves them together; the scene is posed as MuJoCo poses the model; nothing
leaves the machine and the console stays clean. Screenshots go to build/screenshots/.
"""

from __future__ import annotations

import io
import time

import mujoco
import numpy as np
import pytest
from mcap.reader import make_reader

from labd.recorder.summary import decode
from repository.well_known import SUMMARY
from tests.helpers.githttp import GitRepo
from tests.integration.browser import browser, watched
from tests.integration.test_browser import server, shot, wait_ended

__all__ = ["browser", "server", "watched"]
pytestmark = [pytest.mark.integration, pytest.mark.timeout(400)]

MAZE = """\
from controllers.client import EpisodeOver, Lab

with Lab.connect() as lab:
    lab.subscribe("/camera/image/compressed", "sensor_msgs/msg/CompressedImage")
    try:
        for tick in range(80):
            turn = 1.2 if 25 <= tick < 40 else 0.0
            lab.publish("/cmd_vel", "geometry_msgs/msg/Twist",
                        {"linear": {"x": 0.0 if turn else 0.15}, "angular": {"z": turn}})
            lab.step()
    except EpisodeOver:
        pass
"""

PR2 = """\
from controllers.client import EpisodeOver, Lab

READY = [0.66, -0.18, 1.34, -1.65, 1.37, -1.78, 2.1]
JOINTS = ["l_shoulder_pan_joint", "l_shoulder_lift_joint", "l_upper_arm_roll_joint",
          "l_elbow_flex_joint", "l_forearm_roll_joint", "l_wrist_flex_joint",
          "l_wrist_roll_joint"]
with Lab.connect() as lab:
    lab.publish("/torso/command", "trajectory_msgs/msg/JointTrajectory",
                {"joint_names": ["torso_lift_joint"],
                 "points": [{"positions": [0.2], "time_from_start": {"sec": 2}}]})
    lab.publish("/left_arm/command", "trajectory_msgs/msg/JointTrajectory",
                {"joint_names": JOINTS,
                 "points": [{"positions": READY, "time_from_start": {"sec": 3}}]})
    try:
        for tick in range(70):
            lab.step()
    except EpisodeOver:
        pass
"""


def repository(tmp_path, name, task, code):
    toml = f'[controller]\ncommand = ["python", "c.py"]\ntask = "{task}"\n'
    return GitRepo.create(tmp_path / name, {"lab.toml": toml, "c.py": code})


def submit(server, watched, path):
    page = watched.page
    page.goto(server.http_url("/submit"))
    page.fill("#repository", str(path))
    page.click("form.card button[type=submit]")
    page.wait_for_url("**/trials/*")
    return int(page.url.rsplit("/", 1)[1])


def drawn(page, parts):
    condition = " && ".join(f"(d.dataset.drawn || '').includes('{p}')" for p in parts)
    page.wait_for_function(f"(d => {condition})(document.getElementById('record'))", timeout=60_000)


def pixels(page, selector):
    """A fingerprint of a canvas: its pixels' sum and spread (2D canvases only)."""
    return page.evaluate(
        """s => { const c = document.querySelector(s);
                  const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
                  let sum = 0, sq = 0;
                  for (let i = 0; i < d.length; i += 4) { sum += d[i]; sq += d[i] * d[i]; }
                  const n = d.length / 4; return [sum, Math.sqrt(sq / n - (sum / n) ** 2)]; }""",
        selector,
    )


def assert_posed_as_mujoco_poses(page, server, trial_id, body, point):
    """The page's forward kinematics of ``body`` at ``point`` is MuJoCo's."""
    service = server.lab.service
    summary = decode(service.store.read_bytes(service.index.derived(trial_id)[SUMMARY].digest))
    scene = summary["scene"]
    page.evaluate("t => window.labRecord.seek(t)", summary["t"][point])
    shown = page.evaluate("b => window.labRecord.bodyPose(b)", body)
    trial = service.index.trial(trial_id)
    model = model_of(service, trial)
    data = mujoco.MjData(model)
    qpos = np.array(scene["qpos0"])
    qpos[scene["moving"]] = scene["qpos"][point]
    data.qpos[:] = qpos
    mujoco.mj_kinematics(model, data)
    b = model.body(body).id
    assert shown[:3] == pytest.approx(data.xpos[b].tolist(), abs=2e-3)
    w, x, y, z = data.xquat[b]
    assert abs(float(np.dot(shown[3:], [x, y, z, w]))) == pytest.approx(1.0, abs=1e-3)


def model_of(service, trial):
    assert trial.mcap is not None
    stream = io.BytesIO(service.store.read_bytes(trial.mcap))
    attachments = {a.name: a.data for a in make_reader(stream).iter_attachments()}
    assets = {k[6:]: v for k, v in attachments.items() if k.startswith("model/")}
    return mujoco.MjModel.from_xml_string(attachments["model.xml"].decode(), assets)


def test_a_trials_record_in_its_page(server, watched, tmp_path):
    """A person opens a maze trial that watched its camera and a PR2 trial: plots, camera
    frames, the map and the path, and the 3D scene appear, move with the scrubber, come
    from the summary (a small fraction of the record), and nothing leaves the machine."""
    service = server.lab.service
    token = service.index.add_user("alice")
    page = watched.page
    page.goto(server.http_url("/session?then=/submit"))
    page.fill("input[name=token]", token)
    page.click("#token-signin button[type=submit]")
    page.wait_for_url("**/submit")
    maze = submit(server, watched, repository(tmp_path, "maze", "icreate-maze", MAZE).path)
    pr2 = submit(server, watched, repository(tmp_path, "pr2", "pr2-table", PR2).path)
    for trial_id in (maze, pr2):
        assert wait_ended(server, trial_id, timeout=180).mcap
        deadline = time.monotonic() + 60  # the worker files the summary right after
        while SUMMARY not in service.index.derived(trial_id):
            assert time.monotonic() < deadline, f"trial {trial_id} has no summary"
            time.sleep(0.1)

    sizes = {}
    page.on("response", lambda r: sizes.__setitem__(r.url, r.headers.get("content-length")))
    page.goto(server.http_url(f"/trials/{maze}"))
    drawn(page, ["plots", "camera", "map", "scene"])
    assert page.locator("#record .plot canvas").count() >= 8
    titles = page.locator("#record .u-title").all_inner_texts()
    assert "/odom · pose (observation)" in titles and "/cmd_vel · linear (command)" in titles
    camera = page.locator("#record-camera")
    assert camera.is_visible() and pixels(page, "#record-camera")[1] > 5  # an image, not blank
    assert "frame 1 of" in page.locator("#record figure.camera").inner_text()
    start_map = pixels(page, "#record-map")
    start_frame = pixels(page, "#record-camera")
    page.evaluate("window.labRecord.seek(window.labRecord.summary.duration)")
    assert pixels(page, "#record-map") != start_map  # the robot's marker moved along
    assert pixels(page, "#record-camera") != start_frame
    last = page.evaluate("window.labRecord.summary.camera.t.length")
    assert f"frame {last} of {last}" in page.locator("#record figure.camera").inner_text()
    path = page.evaluate("window.labRecord.summary.map.path")
    assert len(path["x"]) > 10 and (path["x"][0], path["y"][0]) == (0, 0)
    points = page.evaluate("window.labRecord.summary.t.length")
    assert_posed_as_mujoco_poses(page, server, maze, "base_link", points - 1)
    summary_url = server.http_url(f"/api/trials/{maze}/summary")
    record_size = service.index.trial(maze).mcap_size
    assert int(sizes[summary_url]) < record_size / 10
    assert not any("data.mcap" in u for u in sizes)  # the page never fetched the record
    page.evaluate("window.labRecord.seek(window.labRecord.summary.duration * 0.7)")
    shot(watched, "record-maze")

    page.goto(server.http_url(f"/trials/{pr2}"))
    drawn(page, ["plots", "scene"])
    titles = page.locator("#record .u-title").all_inner_texts()
    assert "/joint_states · position (observation)" in titles
    assert page.locator("#record-camera").count() == 0  # no one watched its camera
    assert page.locator("#record-scene").is_visible()
    points = page.evaluate("window.labRecord.summary.t.length")
    for point in (0, points // 2, points - 1):  # the arm moves through the ready pose
        assert_posed_as_mujoco_poses(page, server, pr2, "l_wrist_roll_link", point)
    page.evaluate("window.labRecord.seek(window.labRecord.summary.duration)")
    shot(watched, "record-pr2")
    watched.check()
