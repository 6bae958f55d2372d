"""``/metrics`` and ``/readyz`` of a real lab: a trial run by its worker (bubblewrap), a
client of its bridge that drives the live maze robot, each counted in the metrics as
Prometheus' own parser reads them, and every documented metric there.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable

import httpx
import pytest
from prometheus_client.parser import text_string_to_metric_families
from websockets.sync.client import connect

from repository.trial import TrialRequest
from tests.helpers.githttp import GitRepo
from tests.helpers.labs import MAZE, ServerThread, lab_config, running
from tests.integration.test_browser import wait_ended
from tests.integration.test_page_headers import STEPS
from tests.labd.test_metrics import documented, samples

pytestmark = [pytest.mark.integration, pytest.mark.timeout(400)]

TOML = '[controller]\ncommand = ["python", "c.py"]\ntask = "icreate-maze"\n'
ROBOT = (("robot", "icreate-1"),)


def scrape(server: ServerThread) -> str:
    answer = httpx.get(server.http_url("/metrics"), timeout=30)
    assert answer.status_code == 200
    return answer.text


def until(check: Callable[[], bool], timeout: float = 120) -> None:
    """Wait until ``check()`` holds (each try is a request to the lab), or fail."""
    deadline = time.monotonic() + timeout
    while not check():
        assert time.monotonic() < deadline, "not within the time allowed"
        time.sleep(0.2)


def test_a_trial_a_bridge_client_and_a_driver_are_counted(tmp_path, cache):
    """After a trial ran through the lab, /metrics (parsed by Prometheus' parser) counts it
    by its outcome, has its wall time in the histogram and its replay's verdict; a client
    of the bridge is counted while connected, with the frames it sent and was sent, and
    as the live robot's driver while it drives; /readyz names the lab's own worker; and
    every documented metric is in the output, nothing undocumented."""
    with running(lab_config(tmp_path / "data", (MAZE,), workers=1, cache=cache)) as server:
        assert server.lab is not None and server.lab.service is not None
        service = server.lab.service
        ready = httpx.get(server.http_url("/readyz"), timeout=30)
        assert ready.status_code == 200, ready.text
        assert ready.json()["checks"]["workers"] == "workers ready: 1 in this process"

        repo = GitRepo.create(tmp_path / "repo", {"lab.toml": TOML, "c.py": STEPS})
        service.index.add_user("alice")
        alice = service.index.user("alice")
        made = service.submissions.submit(alice, TrialRequest(repository=str(repo.path)))
        service.wake()
        trial = wait_ended(server, made, timeout=180)
        assert trial.outcome is not None and trial.wall_seconds is not None, trial.reason
        until(lambda: sum(samples(scrape(server))["labd_replay_verdicts_total"].values()) == 1)

        with connect(server.url + "/robots/icreate-1") as client:
            client.send(json.dumps({"op": "subscribe", "topic": "/odom"}))
            client.send(
                json.dumps(
                    {"op": "advertise", "topic": "/cmd_vel", "type": "geometry_msgs/msg/Twist"}
                )
            )
            client.send(
                json.dumps({"op": "publish", "topic": "/cmd_vel", "msg": {"linear": {"x": 0.1}}})
            )
            assert json.loads(client.recv(timeout=30))["topic"] == "/odom"
            drive = server.lab.drives["icreate-1"]
            server.wait_until(lambda: drive.current is not None)
            connected = samples(scrape(server))
        server.wait_until(lambda: server.lab.bridge.traffic["icreate-1"].clients == 0)
        text = scrape(server)
    after = samples(text)

    finished = ("kind", "trial"), ("outcome", trial.outcome.value), ("status", "finished")
    assert after["labd_trials"][finished] == 1
    assert after["labd_queue_depth"] == {(): 0.0}
    assert after["labd_trial_wall_seconds_count"] == {(): 1.0}
    assert after["labd_trial_wall_seconds_sum"][()] == pytest.approx(trial.wall_seconds)
    verdicts = {dict(k)["verdict"]: v for k, v in after["labd_replay_verdicts_total"].items()}
    # the trial's (counted alone above); the drive's demonstration, once filed, is
    # replayed by the lab too, and may be counted by now
    assert verdicts["verified"] in (1, 2), verdicts
    assert after["labd_workers"][("kind", "in_process"), ("state", "ok")] == 1

    assert connected["labd_bridge_clients"][ROBOT] == 1
    assert connected["labd_bridge_messages_received_total"][ROBOT] == 3
    assert connected["labd_bridge_messages_sent_total"][ROBOT] >= 1
    assert connected["labd_live_drivers"][ROBOT] == 1
    assert after["labd_bridge_clients"][ROBOT] == 0
    assert after["labd_live_drivers"][ROBOT] == 0
    assert after["labd_bridge_messages_received_total"][ROBOT] == 3

    shown: dict[str, str] = {}
    docs = documented()
    for family in text_string_to_metric_families(text):
        name = family.name + ("_total" if family.type == "counter" else "")
        if not (name.endswith("_created") and name.removesuffix("_created") in docs):
            shown[name] = family.type
    assert shown == docs
    assert "alice" not in text  # counts, never names
