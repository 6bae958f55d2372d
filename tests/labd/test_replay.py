"""Replay: a record re-simulated from its actions alone gives its observations back, byte
for byte; one edited message, another model, another simulator or a cut file is named."""

from __future__ import annotations

import json
from pathlib import Path

import av
import pytest
from mcap.reader import make_reader
from mcap.writer import Writer

from labd.replay import ReplayError, replay
from labd.video import Video, VideoError, VideoSpec
from repository.well_known import MANIFEST_KEY, MANIFEST_RECORD
from tests.labd.test_recorder import record

MAZE = "icreate-maze"


def test_a_record_replays_identically(registry, tmp_path):
    """A maze record, camera included, replays with every message identical."""
    run = record(registry, tmp_path / "a", MAZE, seed=3, ticks=15, camera=True, manifest=True)
    verdict = replay(run.summary.path)
    assert verdict.verified, verdict
    assert verdict.ticks == 15
    assert verdict.compared == sum(run.summary.counts.values()) - run.summary.counts.get(
        "/cmd_vel", 0
    )
    assert str(verdict).startswith("replay verified: 15 ticks")


def test_steps_after_the_episodes_end_replay(registry, tmp_path):
    """A controller that steps on past the end (told each time that the episode is over)
    leaves commands after the last tick; its record replays, with the episode's ticks."""
    run = record(
        registry, tmp_path / "a", MAZE, seed=3, ticks=13, params={"time_limit": 1}, manifest=True
    )
    assert run.robot.sim.tick == 10
    verdict = replay(run.summary.path)
    assert verdict.verified, verdict
    assert verdict.ticks == 10


def rewrite(source: Path, dest: Path, change=None, edit_manifest=None) -> Path:
    """Copy an MCAP record, passing each message's data through ``change`` and its
    manifest through ``edit_manifest``."""
    with source.open("rb") as stream, dest.open("wb") as out:
        reader = make_reader(stream)
        summary = reader.get_summary()
        writer = Writer(out)
        writer.start(profile="ros2")
        for schema in summary.schemas.values():
            writer.register_schema(schema.name, schema.encoding, schema.data)
        for channel in summary.channels.values():
            writer.register_channel(
                channel.topic, channel.message_encoding, channel.schema_id, channel.metadata
            )
        stream.seek(0)
        for metadata in make_reader(stream).iter_metadata():
            values = dict(metadata.metadata)
            if metadata.name == MANIFEST_RECORD and edit_manifest is not None:
                manifest = json.loads(values[MANIFEST_KEY])
                edit_manifest(manifest)
                values[MANIFEST_KEY] = json.dumps(manifest)
            writer.add_metadata(metadata.name, values)
        stream.seek(0)
        for schema, channel, message in make_reader(stream).iter_messages(log_time_order=False):
            data = message.data if change is None else change(schema, channel, message)
            writer.add_message(
                channel.id, message.log_time, data, message.publish_time, message.sequence
            )
        writer.finish()
    return dest


def test_an_edited_observation_is_named_with_both_values(registry, tmp_path):
    """One /odom message changed: replay names its tick, the field and both values."""
    run = record(registry, tmp_path / "a", MAZE, seed=3, ticks=12, manifest=True)
    seen = {"odom": 0}

    def change(schema, channel, message):
        if channel.topic != "/odom":
            return message.data
        seen["odom"] += 1
        if seen["odom"] != 6:  # the sixth /odom is tick 5's
            return message.data
        data = bytearray(message.data)
        data[-8] ^= 0x40  # in the last float64 (twist.covariance[35])
        return bytes(data)

    edited = tmp_path / "edited.mcap"
    rewrite(run.summary.path, edited, change)
    verdict = replay(edited)
    assert not verdict.verified
    assert verdict.divergence.tick == 5 and verdict.divergence.topic == "/odom"
    assert "twist.covariance[35] is" in verdict.divergence.what
    assert " recorded, " in verdict.divergence.what and verdict.divergence.what.endswith("replayed")


def test_another_model_or_simulator_is_refused_naming_both(registry, tmp_path):
    """A manifest whose model digest or mujoco version is not this lab's is refused."""
    run = record(registry, tmp_path / "a", MAZE, seed=3, ticks=3, manifest=True)

    def with_manifest(edit):
        return rewrite(run.summary.path, tmp_path / f"m-{edit.__name__}.mcap", edit_manifest=edit)

    def model(m):
        m.update(model_sha256="0" * 64)

    def mujoco(m):
        m["versions"].update(mujoco="2.3.7")

    other_model = with_manifest(model)
    with pytest.raises(ReplayError, match="the task's model is not the one recorded"):
        replay(other_model)
    other_mujoco = with_manifest(mujoco)
    with pytest.raises(ReplayError, match=r"made with mujoco 2\.3\.7, this lab has mujoco"):
        replay(other_mujoco)


def test_a_manifest_without_its_seed_is_refused_never_replayed_as_seed_0(registry, tmp_path):
    """A record whose manifest lacks its seed (or any key the lab writes) is refused,
    naming the key: it is never replayed with a default in its place."""
    run = record(registry, tmp_path / "a", MAZE, seed=3, ticks=3, manifest=True)
    unseeded = rewrite(run.summary.path, tmp_path / "no-seed.mcap", edit_manifest=_drop_seed)
    with pytest.raises(ReplayError, match=r"its manifest cannot be read: manifest\.seed: missing"):
        replay(unseeded)


def _drop_seed(manifest):
    del manifest["seed"]


def test_a_cut_record_says_where_it_stops(registry, tmp_path):
    """A record cut short replays as far as it goes and says the file is cut there."""
    run = record(registry, tmp_path / "a", MAZE, seed=3, ticks=30, manifest=True, chunk_size=4096)
    data = run.summary.path.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) // 2])
    with pytest.raises(ReplayError, match=r"the record is cut short or damaged after tick \d+"):
        replay(cut)


def test_a_video_larger_than_the_camera_leaves_the_verdict_alone(registry, tmp_path):
    """Rendering 640x480 (past the model's framebuffer) still verifies the camera's frames."""
    run = record(registry, tmp_path / "a", MAZE, seed=3, ticks=6, camera=True, manifest=True)
    video = Video(VideoSpec.parse("front", "640x480", 10), tmp_path / "big.mp4")
    verdict = replay(run.summary.path, renderers=[video])
    video.close()
    assert verdict.verified, verdict
    assert video.frames == 7


def test_videos_are_rendered_after_the_fact(registry, tmp_path):
    """A camera nobody subscribed to, and the whole scene, are rendered during a replay."""
    run = record(registry, tmp_path / "a", MAZE, seed=3, ticks=20, manifest=True)
    videos = [
        Video(VideoSpec.parse("front", "160x120", 10), tmp_path / "front.mp4"),
        Video(VideoSpec.parse("scene", "160x120", 5), tmp_path / "scene.mp4"),
    ]
    verdict = replay(run.summary.path, renderers=videos)
    for video in videos:
        video.close()
    assert verdict.verified
    with av.open(str(tmp_path / "front.mp4")) as container:
        frames = list(container.decode(video=0))
    assert len(frames) == videos[0].frames == 21  # ticks 0 to 20: 10 Hz control, 10 fps
    assert (frames[0].width, frames[0].height) == (160, 120)
    assert videos[1].frames == 11  # every other tick
    with pytest.raises(VideoError, match="WIDTHxHEIGHT"):
        VideoSpec.parse("front", "big")
    wrong = Video(VideoSpec.parse("rear"), tmp_path / "rear.mp4")
    with pytest.raises(VideoError, match="its cameras are front"):
        replay(run.summary.path, renderers=[wrong])
    assert not (tmp_path / "rear.mp4").exists()
