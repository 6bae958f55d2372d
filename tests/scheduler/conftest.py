"""Fixtures for trials for real: the runtime cache, both sandboxes and the lab's side
are shared by every test (tests/conftest.py, tests/helpers/sandboxes.py)."""
