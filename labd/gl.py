"""Rendering's GL contexts and threads.

dm_control's EGL contexts stay current on the thread that last rendered with them, and
one freed on another thread fails (``EGL_BAD_ACCESS``): a simulation nobody closed is
freed by whichever thread the garbage collector happens to run on, a lab's loop thread
or the main one. So after each frame the lab makes the context current on no thread.
"""

from __future__ import annotations

import sys
import threading
from typing import Any


def release(physics: Any) -> None:
    """Make ``physics``'s GL context current on no thread, if this thread holds it (after
    rendering), so that any thread may free it later. EGL only: other backends' contexts
    are left as dm_control keeps them."""
    contexts = getattr(physics, "_contexts", None)
    if contexts is None:
        return
    context = contexts.gl
    if type(context).__name__ != "EGLContext":
        return
    thread = threading.current_thread()
    # dm_control's modules, loaded by now (importing them here could pick the backend
    # before MUJOCO_GL is set: labd.sim sets its default)
    gl_base = sys.modules["dm_control._render.base"]
    if gl_base._CURRENT_THREAD_FOR_CONTEXT.get(id(context)) is not thread:
        return
    renderer = sys.modules[type(context).__module__]  # egl_renderer
    egl = renderer.EGL
    egl.eglMakeCurrent(
        renderer.EGL_DISPLAY, egl.EGL_NO_SURFACE, egl.EGL_NO_SURFACE, egl.EGL_NO_CONTEXT
    )
    del gl_base._CURRENT_THREAD_FOR_CONTEXT[id(context)]
    del gl_base._CURRENT_CONTEXT_FOR_THREAD[thread]
