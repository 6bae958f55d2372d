"""Publishes its own debug type (planner_msgs/msg/Debug, from planner_msgs/) for three ticks.

It prints what the lab's rosapi says of the type, as JSON, so a test can check that the
trial's graph knows it.
"""

import json

from controllers.client import Lab

with Lab.connect() as lab:
    details = lab.call("/rosapi/message_details", {"type": "planner_msgs/Debug"})
    for tick in range(3):
        lab.publish(
            "/planner/debug",
            "planner_msgs/msg/Debug",
            {
                "phase": "search",
                "cost": float(tick),
                "path": [{"x": float(tick), "y": 1.0}],
                "last": {"kind": 1},
            },
        )
        lab.step()

print(json.dumps({"typedefs": details["typedefs"]}))
