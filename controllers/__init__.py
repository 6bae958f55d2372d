"""The controller-side client library and example controllers.

It runs inside the sandbox, so it imports nothing from ``labd``: only the standard
library and ``websockets``. Empty until the trial runner lands (see DESIGN.md).
"""
