"""The trial fixtures of tests/scheduler (the runtime cache, the sandboxes, the lab's side),
shared here, so every test that runs a controller uses the one runtime of the session."""

from __future__ import annotations

from tests.scheduler.conftest import backend, cache, host

__all__ = ["backend", "cache", "host"]
