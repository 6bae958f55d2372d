"""The subcommands of ``labd``, one module each (``labd.cli`` registers them; ``settings``
is ``labd serve``'s table of settings, ``config`` how they are read and shown)."""
