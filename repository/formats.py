"""The export formats, one entry each: the one list the archive, the API, the pages and
the ``labd`` command ask.

A format is an ``ExportFormat`` (``repository.export``) declared by the module that
writes it: its name, its media type, the names of its files and its writer. Adding one
is writing that module and naming it here.
"""

from __future__ import annotations

from repository.errors import ExportError
from repository.export import ExportFormat
from repository.lerobot import LEROBOT
from repository.parquet import PARQUET

FORMATS: dict[str, ExportFormat] = {f.name: f for f in (PARQUET, LEROBOT)}


def export_format(name: str) -> ExportFormat:
    """The format called ``name``; ExportError, naming the formats, if there is none."""
    try:
        return FORMATS[name]
    except KeyError:
        raise ExportError(
            f"unknown format {name!r}: the formats are {', '.join(FORMATS)}"
        ) from None
