"""The ROS 2 nodes that roslibpy's and roslibjs' own test suites expect, as a bridge client.

Their suites run against a ROS 2 system where a launch file started, beside rosbridge,
the tutorials' nodes. Here one ordinary bridge client (plain rosbridge frames over
``websockets``) plays them, so the suites meet the lab as any client would:

- ``/fibonacci``: the tutorials' Fibonacci action server (``--fibonacci-type``:
  ``example_interfaces/action/Fibonacci`` for roslibpy, ``action_tutorials_interfaces/
  action/Fibonacci`` for roslibjs). Order n gives the sequence 0, 1, 1, 2, ... of n + 1
  numbers; from [0, 1] it adds one number per ``--step`` seconds, sending the partial
  sequence as feedback, and stops with status 5 (canceled) when told to cancel;
- ``/add_two_ints`` (``example_interfaces/srv/AddTwoInts``);
- ``/listener``: ``std_msgs/msg/String`` "Hello, World" once a second;
- ``/tf_static``: world -> turtle1, the identity, latched.

``python -m tests.clients.fixtures URL`` prints ``ready`` once all are advertised and
serves until its connection closes or it is interrupted.
"""

from __future__ import annotations

import argparse
import json
import sys
import threading
from typing import Any

from websockets.exceptions import ConnectionClosed
from websockets.sync.client import ClientConnection, connect

FEEDBACK_FIELD = {
    "example_interfaces/action/Fibonacci": "sequence",
    "action_tutorials_interfaces/action/Fibonacci": "partial_sequence",
}


class Fixtures:
    """One bridge connection serving the tutorials' action, service and topics."""

    def __init__(self, socket: ClientConnection, fibonacci_type: str, step: float) -> None:
        self.socket = socket
        self.fibonacci_type = fibonacci_type
        self.step = step
        self.closed = threading.Event()
        self._lock = threading.Lock()
        self._cancelled: dict[str, threading.Event] = {}

    def send(self, frame: dict[str, Any]) -> None:
        with self._lock:
            self.socket.send(json.dumps(frame))

    def advertise(self) -> None:
        self.send({"op": "advertise_action", "action": "/fibonacci", "type": self.fibonacci_type})
        self.send(
            {
                "op": "advertise_service",
                "service": "/add_two_ints",
                "type": "example_interfaces/srv/AddTwoInts",
            }
        )
        self.send({"op": "advertise", "topic": "/listener", "type": "std_msgs/msg/String"})
        self.send(
            {
                "op": "advertise",
                "topic": "/tf_static",
                "type": "tf2_msgs/msg/TFMessage",
                "latch": True,
            }
        )
        identity = {"translation": {}, "rotation": {"w": 1.0}}
        transform = {"header": {"frame_id": "world"}, "child_frame_id": "turtle1"}
        self.send(
            {
                "op": "publish",
                "topic": "/tf_static",
                "msg": {"transforms": [{**transform, "transform": identity}]},
            }
        )
        # A round trip, so everything above is in the graph before "ready".
        self.send({"op": "call_service", "id": "ready", "service": "/rosapi/get_time"})

    def serve(self) -> None:
        threading.Thread(target=self._talk, daemon=True).start()
        try:
            for text in self.socket:
                frame = json.loads(text)
                op = frame.get("op")
                if op == "service_response" and frame.get("id") == "ready":
                    print("ready", flush=True)
                elif op == "call_service":
                    args = frame.get("args") or {}
                    self.send(
                        {
                            "op": "service_response",
                            "id": frame["id"],
                            "service": frame["service"],
                            "values": {"sum": args.get("a", 0) + args.get("b", 0)},
                            "result": True,
                        }
                    )
                elif op == "send_action_goal":
                    cancelled = self._cancelled[frame["id"]] = threading.Event()
                    threading.Thread(
                        target=self._fibonacci, args=(frame, cancelled), daemon=True
                    ).start()
                elif op == "cancel_action_goal":
                    self._cancelled.get(frame["id"], threading.Event()).set()
        except ConnectionClosed:
            pass
        finally:
            self.closed.set()

    def _fibonacci(self, frame: dict[str, Any], cancelled: threading.Event) -> None:
        goal_id, order = frame["id"], int(frame["args"].get("order", 0))
        sequence = [0, 1]
        status = 4  # succeeded
        for _ in range(1, order):
            if cancelled.wait(self.step):
                status = 5
                break
            sequence.append(sequence[-1] + sequence[-2])
            self._safely(
                {
                    "op": "action_feedback",
                    "id": goal_id,
                    "action": "/fibonacci",
                    "values": {FEEDBACK_FIELD[self.fibonacci_type]: sequence},
                }
            )
        self._cancelled.pop(goal_id, None)
        self._safely(
            {
                "op": "action_result",
                "id": goal_id,
                "action": "/fibonacci",
                "values": {"sequence": sequence},
                "status": status,
                "result": True,
            }
        )

    def _talk(self) -> None:
        while not self.closed.wait(1.0):
            self._safely({"op": "publish", "topic": "/listener", "msg": {"data": "Hello, World"}})

    def _safely(self, frame: dict[str, Any]) -> None:
        try:
            self.send(frame)
        except ConnectionClosed:
            self.closed.set()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("url")
    parser.add_argument("--fibonacci-type", choices=sorted(FEEDBACK_FIELD), required=True)
    parser.add_argument("--step", type=float, default=0.5, help="seconds per number")
    args = parser.parse_args(argv)
    with connect(args.url, max_size=None) as socket:
        fixtures = Fixtures(socket, args.fibonacci_type, args.step)
        fixtures.advertise()
        fixtures.serve()
    return 0


if __name__ == "__main__":
    sys.exit(main())
