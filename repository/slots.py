"""A reservation's state, as the API shows it and the ``labd`` command reads it back.

``repository.reservations`` decides it (``Reservation.state``) on the index; the word
lives here, apart from the index and SQLAlchemy, so that a client that reads
reservations imports neither.
"""

from __future__ import annotations

from typing import Literal

# upcoming: it starts later; current: its key opens the robot now; ended: its time is
# over; released: its holder ended it early (or cancelled it before it began)
State = Literal["upcoming", "current", "ended", "released"]
