"""A live robot driven by real clients: one drives, one watches and is refused, and the
drive lands in the archive as a demonstration that replays."""

from __future__ import annotations

import json
import time

import httpx
import pytest
import roslibpy
from websockets.sync.client import connect as connect_ws

from labd.replay import replay
from repository.index import Filters
from repository.trial import Kind
from tests.helpers.labs import ServerThread, lab_config, running

pytestmark = [pytest.mark.integration, pytest.mark.timeout(120)]
TWIST = "geometry_msgs/msg/Twist"


@pytest.fixture
def server(tmp_path):
    """A lab with the live maze robot and the archive, no worker."""
    with running(lab_config(tmp_path / "data")) as server:
        yield server


def connect(server: ServerThread) -> roslibpy.Ros:
    ros = roslibpy.Ros(host=server.url + "/robots/icreate-1")
    ros.run(timeout=10)
    return ros


def test_a_drive_in_a_real_lab_is_a_demonstration(server, tmp_path):
    """A roslibpy client takes control with /lab/drive and drives; a second client's
    commands are refused; when the driver leaves, its drive is a demonstration trial
    filed under the lab's name for it, with the session, interface and claimed user in
    its manifest, and its record replays."""
    driver, watcher = connect(server), connect(server)
    try:
        seen = []
        roslibpy.Topic(watcher, "/lab/driver", "lab_msgs/msg/Driver").subscribe(seen.append)
        answer = roslibpy.Service(driver, "/lab/drive", "lab_msgs/srv/Drive").call(
            roslibpy.ServiceRequest({"session": "s-1", "interface": "video", "user": "ann"}),
            timeout=10,
        )
        assert answer["success"], answer
        cmd = roslibpy.Topic(driver, "/cmd_vel", TWIST)
        with connect_ws(server.url + "/robots/icreate-1") as other:  # a plain client, watching
            other.send(json.dumps({"op": "set_level", "level": "error"}))
            other.send(json.dumps({"op": "advertise", "topic": "/cmd_vel", "type": TWIST}))
            other.send(
                json.dumps({"op": "publish", "topic": "/cmd_vel", "msg": {"linear": {"x": -1}}})
            )
            status = json.loads(other.recv(timeout=10))
        assert status["op"] == "status"
        assert "icreate-1 is driven by guest:client_" in status["msg"]
        assert "; you are watching" in status["msg"]
        odom = []
        roslibpy.Topic(driver, "/odom", "nav_msgs/msg/Odometry").subscribe(odom.append)
        deadline = time.monotonic() + 20
        while len(odom) < 30 and time.monotonic() < deadline:
            cmd.publish(roslibpy.Message({"linear": {"x": 0.2}}))
            time.sleep(0.05)
        assert len(odom) >= 30
        assert any(m["driver"].startswith("guest:") and m["interface"] == "video" for m in seen)
    finally:
        driver.close()
    service = server.lab.service
    deadline = time.monotonic() + 30
    while not (found := service.index.find(Filters(kind=Kind.DEMONSTRATION)).items):
        assert time.monotonic() < deadline, "no demonstration filed"
        time.sleep(0.1)
    watcher.close()
    [demo] = found
    assert (demo.task, demo.repository) == ("icreate-maze", "robot:icreate-1")
    assert demo.submitter.startswith("guest:client_")  # the lab's name: no key said who
    assert demo.reason.startswith("the driver left at tick")
    assert demo.manifest["driver"] == {
        "user": demo.submitter,
        "claimed_user": "ann",  # what the client typed, kept apart
        "interface": "video",
        "session": "s-1",
    }
    assert demo.signature is not None
    record = tmp_path / "demo.mcap"
    service.store.copy_to(demo.mcap, record)
    verdict = replay(record)
    assert verdict.verified, verdict
    deadline = time.monotonic() + 60  # the lab replays a drive once it has filed it
    while "replay.json" not in (made := service.index.derived(demo.id)):
        assert time.monotonic() < deadline, made
        time.sleep(0.1)
    assert json.loads(service.store.read_bytes(made["replay.json"].digest))["verified"] is True
    video = httpx.get(server.http_url(f"/api/trials/{demo.id}/video"), timeout=120)
    assert video.status_code == 200 and video.headers["content-type"] == "video/mp4"
    assert service.index.derived(demo.id)["video.mp4"].size == len(video.content)
    assert verdict.ticks >= 29  # the 30 odometry messages seen: ticks 0 to 29, at least
