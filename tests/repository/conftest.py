"""The archive's tests share an empty index, on each database, as the lab opens it."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from repository.index import Index


@pytest.fixture
def index(database_url: str) -> Iterator[Index]:
    """An empty index on each database (``Index.open``: the real time; tests of leases,
    quotas and expiries take ``clocked_index``)."""
    index = Index.open(database_url)
    yield index
    index.close()
