"""Integration tests share the root conftest's fixtures (the sandboxes, the lab's side)."""
