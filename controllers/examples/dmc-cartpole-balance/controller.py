"""Balance dm_control's cart-pole (the lab's ``dmc-cartpole-balance``) with a linear policy.

The pole starts nearly upright; the task pays up to 1 a step for keeping it upright with
the cart near the centre, little control and a slow pole, over 1000 steps of 0.01 s, and
succeeds at a return of 900 (docs/tasks.md, "The dm_control suite pack"). Doing nothing
earns about 750: the pole falls.

The policy is one line of linear algebra: the action is ``GAINS . state`` clipped to
[-1, 1], where the state is the task's Gymnasium observation (``labd/dmc-cartpole-balance-v1``:
``position`` (the cart's position, the pole's cosine and sine) then ``velocity`` (the
cart's and the pole's)). The gains were tuned in-process through Gymnasium (README.md);
on the 20 dev seeds every episode returns 999.2 to 999.98.

**Bit for bit with Gymnasium.** The environment's observation is float32, so the policy
was tuned, and is computed here, in float32: the float64 values of ``/observation/*`` are
rounded to float32 first, the dot product is taken in float32, and that float32 result is
sent (exactly: a float32 is a float64, and JSON carries a float64 exactly). The lab casts
nothing, so the physics gets the very action ``env.step`` got, and the rewards equal the
environment's, bit for bit. The same policy computed in float64 differs in the last bits
from the first tick, and so do the rewards.

It uses NumPy and the lab's client library only, and nothing random or timed, so the same
seed gives the same run.
"""

from __future__ import annotations

import sys

import numpy as np

from controllers.client import EpisodeOver, Lab

ARRAY = "std_msgs/msg/Float64MultiArray"
# The Gymnasium observation's order: position.0..2 (cart x, pole cos, pole sin), then
# velocity.0..1 (cart, pole). The cosine's gain is 0: it is near 1 whenever the pole is up.
GAINS = np.array([0.2, 0.0, 4.0, 0.4, 0.6], dtype=np.float32)


def act(position: list[float], velocity: list[float]) -> float:
    """The action for one tick, computed as in training: float32 throughout."""
    state = np.array(position + velocity, dtype=np.float32)
    action = np.clip(GAINS @ state, np.float32(-1), np.float32(1))
    return float(action)  # the float32 value, exactly


def main() -> int:
    with Lab.connect() as lab:
        position = lab.subscribe("/observation/position", ARRAY)
        velocity = lab.subscribe("/observation/velocity", ARRAY)
        while True:
            # the newest tick's (tick 0's is latched: the first get waits for it)
            action = act(position.get()["data"], velocity.get()["data"])
            lab.publish("/action", ARRAY, {"data": [action]})
            try:
                lab.step()  # the subscriptions then hold this tick's observations
            except EpisodeOver as over:
                print(f"episode over: {over.tick.message}")
                return 0


if __name__ == "__main__":
    sys.exit(main())
