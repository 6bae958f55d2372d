"""The simulated robots and their tasks (dm_control on MuJoCo).

Cameras render headless: unless told otherwise, MuJoCo uses EGL (Mesa's CPU
rasteriser on a machine without a GPU). The variable must be set before dm_control
is imported, which is why this package sets its default.
"""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "egl")
