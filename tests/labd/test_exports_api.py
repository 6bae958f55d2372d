"""Exports through the API: many trials as one dataset, chosen as [data] chooses them."""

from __future__ import annotations

import io
import json
import zipfile

import pyarrow.parquet as pq
import pytest

from labd.graph.types import TypeRegistry
from labd.live import Driving
from labd.scripted import demonstrate
from labd.station import Station
from repository.index import Filters
from tests.labd.test_api import api, service  # noqa: F401 (fixtures)


@pytest.fixture
def demonstrations(service, tmp_path):  # noqa: F811
    """Two scripted demonstrations filed in the service's archive."""
    station = Station(TypeRegistry.default(), "icreate-1", "icreate-maze", {}, 0, live=True,
                      protected_prefixes=())  # fmt: skip
    driving = Driving(station, work=tmp_path / "live", file=service.file_demonstration)
    try:
        for seed in (3, 5):
            demonstrate(station, driving, user="ann", seed=seed)
    finally:
        driving.close()
        station.close()
    return [t.id for t in reversed(service.index.find(Filters()).items)]


async def test_many_trials_export_as_one_signed_dataset(api, demonstrations):  # noqa: F811
    """GET /api/exports/parquet?kind=demonstration: a zip of one Parquet file, an episode
    per demonstration with its provenance, every tick from 0, and the lab's signature."""
    answer = await api.get("/api/exports/parquet", params={"kind": "demonstration"})
    assert answer.status_code == 200, answer.text
    with zipfile.ZipFile(io.BytesIO(answer.content)) as archive:
        names = set(archive.namelist())
        assert names == {"data.parquet", "labd-signature.json"}
        table = pq.read_table(io.BytesIO(archive.read("data.parquet")))
        signed = json.loads(archive.read("labd-signature.json"))
    episodes = json.loads(table.schema.metadata[b"labd.episodes"])
    assert [e["trial"] for e in episodes] == demonstrations
    assert {e["kind"] for e in episodes} == {"demonstration"}
    frames = table.column("frame_index").to_pylist()
    assert frames[0] == 0 and frames.count(0) == 2
    assert signed["statement"]["trials"][0]["trial"] == demonstrations[0]


async def test_an_export_query_that_matches_nothing_is_refused(api, demonstrations):  # noqa: F811
    """A query that matches nothing, or no query at all, is a 422 saying so."""
    nothing = await api.get("/api/exports/lerobot", params={"task": "pr2-table"})
    assert nothing.status_code == 422
    assert "matches no public, finished trial" in nothing.json()["error"]
    bare = await api.get("/api/exports/lerobot")
    assert bare.status_code == 422 and "name trials" in bare.json()["error"]
