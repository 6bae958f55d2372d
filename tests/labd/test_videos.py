"""A record's video: rendered by the service when first asked for (or in the background),
kept beside the record, and served from the store after; what cannot be rendered is
a clear 404, remembered; a slow render is a 503 that asks to come back."""

from __future__ import annotations

import asyncio
import io
import time

import av
import pytest

from labd.trial import LabHost
from labd.videos import Videos
from repository.index import Derived
from repository.trial import Order
from repository.well_known import REPLAY, VIDEO
from tests.labd.test_api import api, service  # noqa: F401  (fixtures)
from tests.labd.test_recorder import record
from tests.labd.test_summaries_api import file_trial

PATH = "/api/trials/{}/video"


@pytest.fixture(scope="module")
def replayable(registry, tmp_path_factory):
    """A short maze drive recorded as a trial records it, manifest and all."""
    run = record(registry, tmp_path_factory.mktemp("replayable"), "icreate-maze", ticks=40,
                 manifest=True)  # fmt: skip
    return run.summary.path


@pytest.fixture(scope="module")
def unreplayable(registry, tmp_path_factory):
    """A record without a manifest: nothing says which task to rebuild."""
    return record(registry, tmp_path_factory.mktemp("bare"), "icreate-maze", ticks=5).summary.path


class Counting(LabHost):
    def __init__(self, pause: float = 0.0) -> None:
        super().__init__()
        self.pause = pause
        self.rendered: list[str] = []

    def video(self, mcap, out, *, seconds=None, background=True):
        time.sleep(self.pause)
        self.rendered.append("background" if background else "asked")
        return super().video(mcap, out, seconds=seconds, background=background)


def frames(data: bytes) -> int:
    with av.open(io.BytesIO(data)) as container:
        return sum(1 for _ in container.decode(video=0))


async def test_a_video_is_rendered_when_first_asked_for_then_served_as_kept(
    api,  # noqa: F811
    service,  # noqa: F811
    replayable,
):
    service.videos.host = host = Counting()
    trial_id = file_trial(service, replayable)
    assert VIDEO not in service.index.derived(trial_id)
    first = await api.get(PATH.format(trial_id))
    assert first.status_code == 200 and first.headers["content-type"] == "video/mp4"
    assert frames(first.content) == 41  # ticks 0 to 40, 0.1 s apart, at 10 frames a second
    kept = service.index.derived(trial_id)[VIDEO]
    assert kept.size == len(first.content) and kept.media_type == "video/mp4"
    again = await api.get(PATH.format(trial_id))
    assert again.content == first.content
    assert host.rendered == ["asked"]  # once, at the asker's priority


async def test_two_asking_at_once_share_one_render(api, service, replayable):  # noqa: F811
    service.videos.host = host = Counting(pause=0.5)
    trial_id = file_trial(service, replayable)
    one, two = await asyncio.gather(api.get(PATH.format(trial_id)), api.get(PATH.format(trial_id)))
    assert one.status_code == two.status_code == 200 and one.content == two.content
    assert host.rendered == ["asked"]


async def test_a_record_that_cannot_be_rendered_is_a_404_saying_why_once(
    api,  # noqa: F811
    service,  # noqa: F811
    unreplayable,
):
    service.videos.host = host = Counting()
    trial_id = file_trial(service, unreplayable)
    first = await api.get(PATH.format(trial_id))
    assert first.status_code == 404
    assert "no camera to render, or cannot be replayed here" in first.json()["error"]
    again = await api.get(PATH.format(trial_id))
    assert again.status_code == 404 and again.json() == first.json()
    assert host.rendered == ["asked"]  # the reason is remembered, not rendered again


async def test_a_slow_render_is_a_503_to_come_back_to_and_goes_on(
    api,  # noqa: F811
    service,  # noqa: F811
    replayable,
    monkeypatch,
):
    monkeypatch.setattr("labd.api.records.ASK_WAIT", 0.2)
    service.videos.host = Counting(pause=1.0)
    trial_id = file_trial(service, replayable)
    answer = await api.get(PATH.format(trial_id))
    assert answer.status_code == 503 and answer.headers["retry-after"] == "10"
    assert "being rendered" in answer.json()["error"]
    async with asyncio.timeout(60):
        while VIDEO not in service.index.derived(trial_id):
            await asyncio.sleep(0.1)
    assert (await api.get(PATH.format(trial_id))).status_code == 200


async def test_a_trial_without_a_record_has_no_video(api, service):  # noqa: F811
    service.index.add_user("bob", max_running=1)
    user = service.index.user("bob")
    order = Order(repository="/r", commit="c" * 40, task="icreate-maze", seed=3, public=True)
    trial_id = service.queue.submit(user, order)
    answer = await api.get(PATH.format(trial_id))
    assert answer.status_code == 404 and "no record" in answer.json()["error"]


async def test_the_background_renders_replayed_records_newest_first(
    service,  # noqa: F811
    replayable,
    tmp_path,
):
    host = Counting()
    made = Videos(service.index, service.store, host, tmp_path / "work", poll=0.1)
    older, newer, unreplayed = (file_trial(service, replayable) for _ in range(3))
    verdict = service.store.put_bytes(b'{"verified": true}')
    for trial_id in (older, newer):
        service.index.put_derived(trial_id, Derived(REPLAY, verdict, 18, "application/json"))
    order: list[int] = []
    stop = asyncio.Event()
    running = asyncio.create_task(made.run(stop))
    try:
        async with asyncio.timeout(120):
            while len(order) < 2:
                for trial_id in (older, newer):
                    if trial_id not in order and VIDEO in service.index.derived(trial_id):
                        order.append(trial_id)
                await asyncio.sleep(0.05)
    finally:
        stop.set()
        await running
    assert order == [newer, older]
    assert host.rendered == ["background", "background"]  # in the idle class
    assert VIDEO not in service.index.derived(unreplayed)  # not verified yet: not rendered
    assert list((tmp_path / "work").iterdir()) == []


async def test_the_background_waits_while_trials_run_or_wait(service, replayable, tmp_path):  # noqa: F811
    busy = [True]
    host = Counting()
    made = Videos(
        service.index, service.store, host, tmp_path / "work", busy=lambda: busy[0], poll=0.1
    )
    trial_id = file_trial(service, replayable)
    verdict = service.store.put_bytes(b'{"verified": true}')
    service.index.put_derived(trial_id, Derived(REPLAY, verdict, 18, "application/json"))
    stop = asyncio.Event()
    running = asyncio.create_task(made.run(stop))
    try:
        await asyncio.sleep(1.0)
        assert host.rendered == []  # the lab is busy: nothing rendered
        busy[0] = False
        async with asyncio.timeout(60):
            while VIDEO not in service.index.derived(trial_id):
                await asyncio.sleep(0.05)
    finally:
        stop.set()
        await running
    assert host.rendered == ["background"]
