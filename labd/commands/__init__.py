"""The subcommands of ``labd``, one module each (``serve`` lives in ``labd.cli``)."""
