"""``python -m labd``: the same as the ``labd`` command."""

import sys

from labd.cli import main

sys.exit(main())
