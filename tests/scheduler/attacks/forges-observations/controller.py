"""Tries to forge the robot's data, then steps honestly; prints the lab's statuses as JSON.

It advertises and publishes /odom with x = 42, publishes /clock without advertising,
and advertises /lab/step, each three times or once, before five honest ticks. With
target.json saying {"forge": false} it does the honest part only, so a test can
compare the two records.
"""

import json
import os
from pathlib import Path

from websockets.sync.client import connect

target = Path("target.json")
forge = json.loads(target.read_text())["forge"] if target.exists() else True
statuses = []

with connect(os.environ["LAB_BRIDGE_URL"]) as ws:

    def send(frame):
        ws.send(json.dumps(frame))

    def answer(call_id):
        while True:
            frame = json.loads(ws.recv(timeout=30))
            if frame["op"] == "status":
                statuses.append(frame)
            elif frame["op"] == "service_response" and frame.get("id") == call_id:
                return frame

    send({"op": "set_level", "level": "error"})
    if forge:
        odom = {"header": {"frame_id": "odom"}, "pose": {"pose": {"position": {"x": 42.0}}}}
        send(
            {"op": "advertise", "topic": "/odom", "type": "nav_msgs/msg/Odometry", "id": "adv-odom"}
        )
        for n in range(3):
            send({"op": "publish", "topic": "/odom", "msg": odom, "id": f"odom-{n}"})
            send(
                {
                    "op": "publish",
                    "topic": "/clock",
                    "msg": {"clock": {"sec": 42}},
                    "id": f"clock-{n}",
                }
            )
        send(
            {
                "op": "advertise_service",
                "service": "/lab/step",
                "type": "std_srvs/srv/Trigger",
                "id": "adv-step",
            }
        )
    for tick in range(1, 6):
        send(
            {
                "op": "publish",
                "topic": "/cmd_vel",
                "msg": {"linear": {"x": 0.1}, "angular": {"z": 0.3}},
            }
        )
        send({"op": "call_service", "service": "/lab/step", "id": f"step-{tick}"})
        assert answer(f"step-{tick}")["result"], "the lab's /lab/step did not answer"
    # A last round trip, so every status sent before it has been read.
    send({"op": "call_service", "service": "/rosapi/get_time", "id": "last"})
    answer("last")

print(json.dumps({"statuses": statuses}))
