"""Test helpers shared by test modules: real git repositories and a git HTTP server."""
