"""A team that stands still (the lab's ``soccer-1v1`` and ``soccer-2v2``): it steps every
tick and never moves, so its players keep their places and never kick. The house's
weakest opponent on a ladder: it loses to any team that scores, and draws with one that
does not, but never forfeits. The lab's client library only.
"""

from __future__ import annotations

import sys

from controllers.client import EpisodeOver, Lab


def main() -> int:
    with Lab.connect() as lab:
        while True:
            try:
                lab.step()
            except EpisodeOver as over:
                print(f"episode over: {over.tick.message}")
                return 0


if __name__ == "__main__":
    sys.exit(main())
