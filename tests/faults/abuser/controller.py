"""Abuses the bridge, then steps three times like an honest controller; prints a report.

Run as ``controller.py abuse`` it first

1. publishes FLOOD messages on a topic of its own as fast as it can, while a second
   connection times round trips of ``/rosapi/get_time``;
2. subscribes to SUBSCRIPTIONS topics, more than a client may;
3. tries to provide, as a service and as an action, every service name the lab lists,
   and more names under ``/lab/`` and ``/rosapi/``;

and prints what the lab answered, as JSON. ``controller.py honest`` only steps.
"""

import json
import os
import statistics
import sys
import threading
import time

from websockets.sync.client import connect

FLOOD = 20_000
SUBSCRIPTIONS = 1_500
MORE_NAMES = ["/lab/step", "/lab/reset", "/lab/anything", "lab/step", "rosapi/topics", "/rosapi/x"]
URL = os.environ["LAB_BRIDGE_URL"]


class Client:
    def __init__(self, ws):
        self.ws = ws
        self.statuses = []

    def send(self, frame):
        self.ws.send(json.dumps(frame))

    def answer(self, call_id):
        """Read frames until the reply with ``call_id``; statuses on the way are kept."""
        while True:
            frame = json.loads(self.ws.recv(timeout=60))
            if frame["op"] == "status":
                self.statuses.append(frame)
            elif frame.get("id") == call_id:
                return frame

    def call(self, service, call_id, args=None):
        self.send({"op": "call_service", "service": service, "id": call_id, "args": args or {}})
        return self.answer(call_id)


def probe(stop, round_trips):
    """Round trips of a cheap service call on a connection of its own, until ``stop``."""
    with connect(URL) as ws:
        other, n = Client(ws), 0
        while not stop.is_set():
            began = time.monotonic()
            other.call("/rosapi/get_time", n)
            round_trips.append(time.monotonic() - began)
            n += 1


def flood(lab, report):
    stop, round_trips = threading.Event(), []
    prober = threading.Thread(target=probe, args=(stop, round_trips))
    prober.start()
    while not round_trips:
        time.sleep(0.01)
    began = time.monotonic()
    lab.send({"op": "advertise", "topic": "/flood", "type": "std_msgs/msg/String"})
    for i in range(FLOOD):
        lab.send({"op": "publish", "topic": "/flood", "msg": {"data": f"flood {i}"}})
    lab.call("/rosapi/get_time", "flooded")  # in order: every publish was taken
    report["flood_seconds"] = time.monotonic() - began
    stop.set()
    prober.join()
    during = round_trips[1:]
    report["probe"] = {
        "round_trips": len(during),
        "median": statistics.median(during),
        "max": max(during),
    }


def subscribe_many(lab, report):
    for i in range(SUBSCRIPTIONS):
        frame = {"op": "subscribe", "topic": f"/many/t{i}", "type": "std_msgs/msg/String"}
        lab.send({**frame, "id": f"sub-{i}"})
    lab.call("/rosapi/get_time", "subscribed")
    refused = [s for s in lab.statuses if str(s.get("id", "")).startswith("sub-")]
    report["subscriptions_refused"] = {s["id"]: s["msg"] for s in refused}


def take_lab_names(lab, report):
    listed = lab.call("/rosapi/services", "services")["values"]["services"]
    names = sorted(set(listed) | set(MORE_NAMES))
    for name in names:
        lab.send(
            {
                "op": "advertise_service",
                "service": name,
                "type": "std_srvs/srv/Trigger",
                "id": f"service {name}",
            }
        )
        lab.send(
            {
                "op": "advertise_action",
                "action": name,
                "type": "example_interfaces/action/Fibonacci",
                "id": f"action {name}",
            }
        )
    lab.call("/rosapi/get_time", "advertised")
    refused = [s for s in lab.statuses if str(s.get("id", "")).startswith(("service ", "action "))]
    report["names"] = names
    report["names_refused"] = {s["id"]: s["msg"] for s in refused}
    providers = lab.call("/rosapi/service_providers", "providers", {"service": "/lab/step"})
    report["step_providers"] = providers["values"]["providers"]


with connect(URL, max_size=None) as ws:
    lab = Client(ws)
    report = {}
    lab.send({"op": "set_level", "level": "error"})
    if sys.argv[1] == "abuse":
        flood(lab, report)
        subscribe_many(lab, report)
        take_lab_names(lab, report)
    for tick in range(1, 4):
        lab.send({"op": "publish", "topic": "/cmd_vel", "msg": {"linear": {"x": 0.1}}})
        stepped = lab.call("/lab/step", f"step-{tick}")
        assert stepped["result"] and stepped["values"]["success"], stepped
    report["other_statuses"] = [
        s
        for s in lab.statuses
        if not str(s.get("id", "")).startswith(("sub-", "service ", "action "))
    ]
print(json.dumps(report))
