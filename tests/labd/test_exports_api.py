"""Exports through the API: one trial's, and many trials as one dataset, chosen as [data]
chooses them."""

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
from repository.formats import FORMATS
from repository.index import Filters
from repository.parquet import PARQUET
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


async def test_the_formats_are_the_registrys_in_paths_and_in_the_openapi_document(api):  # noqa: F811
    """A format the registry does not hold is a 422 naming those it holds, and the OpenAPI
    document lists the registry's names and media types."""
    unknown = await api.get("/api/trials/1/export/csv")
    assert unknown.status_code == 422
    assert unknown.json()["error"] == "fmt: Input should be 'parquet' or 'lerobot'"
    spec = (await api.get("/openapi.json")).json()
    route = spec["paths"]["/api/trials/{trial_id}/export/{fmt}"]["get"]
    [fmt] = [p for p in route["parameters"] if p["name"] == "fmt"]
    assert fmt["schema"]["enum"] == list(FORMATS)
    assert set(route["responses"]["200"]["content"]) == {f.media_type for f in FORMATS.values()}


async def test_one_trials_parquet_export_is_its_file_named_and_signed(api, demonstrations):  # noqa: F811
    """GET /api/trials/{id}/export/parquet: the Parquet file itself, under the format's
    media type and file name, kept beside the record under its artifact's name, with its
    signature naming the format."""
    trial = demonstrations[0]
    answer = await api.get(f"/api/trials/{trial}/export/parquet")
    assert answer.status_code == 200, answer.text
    assert answer.headers["content-type"] == PARQUET.media_type
    assert f'filename="trial-{trial}.parquet"' in answer.headers["content-disposition"]
    table = pq.read_table(io.BytesIO(answer.content))
    assert table.column("frame_index").to_pylist()[0] == 0
    signed = (await api.get(f"/api/trials/{trial}/export/parquet/signature")).json()
    assert signed["statement"]["format"] == "parquet"
    assert signed["statement"]["trial"] == trial
    assert set(signed["statement"]["files"]) == {"data.parquet"}
