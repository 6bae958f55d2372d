"""The controller-side client library and example controllers.

It runs inside the sandbox, so it imports nothing from ``labd``: only the standard
library. ``controllers.client.Lab`` is the client (lockstep
stepping, topics, services, errors as exceptions); ``controllers/examples/`` holds
example controllers, each shaped like a user's repository (see DESIGN.md).
"""
