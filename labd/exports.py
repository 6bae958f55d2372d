"""Exports of records for learning, as the lab makes them: its task layouts and its cameras.

``repository.export`` turns records into rows; this module supplies what only the lab
knows: each task's layout (``labd.sim.features``), each record's provenance from its
manifest, and the camera images a record lacks, rendered by replaying it
(``labd.replay``): a record has a camera's JPEG images only from the tick its
controller subscribed (never, for a controller that did not look), and an export has an
image on every row. Rendering is deterministic, so a rendered image is the very JPEG the
lab would have recorded at that tick.

It also writes the data a trial learns from (``scheduler.data``): for each task among
the pinned records, a LeRobot dataset of their state and action (``lerobot/<task>/``)
and the same rows as NumPy arrays (``lerobot/<task>/arrays.npz``).
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow.parquet as pq  # type: ignore[import-untyped]
import simplejpeg

from labd.errors import LabError
from labd.recorder import read_manifest
from labd.replay import ReplayError, replay
from labd.sim import registry
from labd.sim.camera import Camera
from repository.digests import manifest_digest
from repository.errors import ExportError, ManifestError
from repository.export import ExportFormat, ExportSummary, Layout, Source, export
from repository.lerobot import DATA_PATH, EPISODES_PATH, LEROBOT
from repository.manifest import Manifest

log = logging.getLogger("labd.exports")
ARRAYS = "arrays.npz"


def layout(task: str) -> Layout:
    """The export layout ``task`` declares (ExportError if it has none, or is unknown)."""
    found = _layout(task)
    if found is None:
        raise ExportError(f"task {task!r} has no export layout")
    return found


def _layout(task: str) -> Layout | None:
    try:
        return registry.get(task).layout
    except LabError:  # a task this lab does not have (any more): its records are MCAP only
        return None


def _model_camera(task: str) -> str | None:
    try:
        return registry.get(task).camera
    except LabError:
        return None


def provenance_of(mcap: Path, known: Mapping[str, Any]) -> dict[str, Any]:
    """A record's provenance: what the archive knows of it (``known``: trial, kind,
    outcome, digests ...), completed from the manifest it holds."""
    held = read_manifest(mcap)
    manifest = _manifest(held)
    found: dict[str, Any] = {
        "task": manifest.task.name if manifest else None,
        "repository": manifest.repository if manifest else None,
        "commit": manifest.commit if manifest else None,
        "seed": manifest.seed if manifest else None,
        "manifest_digest": manifest_digest(held) if held else None,
    }
    return {**found, **{k: v for k, v in known.items() if v is not None}}


def _manifest(held: dict[str, Any] | None) -> Manifest | None:
    """The manifest a record holds, typed (None: it holds none)."""
    try:
        return None if not held else Manifest.from_json(held)
    except ManifestError as err:
        raise ExportError(f"the record's manifest cannot be read: {err}") from None


class _Frames:
    """A replay renderer keeping JPEG images of one camera at the ticks asked for."""

    def __init__(self, camera: Camera, ticks: Sequence[int]) -> None:
        self.camera = camera
        self.spec = camera  # width and height, for the replay's framebuffer
        self.wanted = set(ticks)
        self.frames: dict[int, bytes] = {}

    def __call__(self, physics: Any, tick: int) -> None:
        if tick in self.wanted:
            pixels = np.ascontiguousarray(self.camera.render(physics))
            self.frames[tick] = simplejpeg.encode_jpeg(
                pixels, quality=self.camera.quality, colorspace="RGB"
            )


def render(mcap: Path, camera: str, ticks: Sequence[int]) -> dict[int, bytes]:
    """JPEG images of ``camera`` at ``ticks``, rendered by replaying the record ``mcap``."""
    manifest = _manifest(read_manifest(mcap))
    task = manifest.task.name if manifest else ""
    params = manifest.parameters if manifest else {}
    model_camera = _model_camera(task)
    if model_camera is None or camera != "camera":
        raise ExportError(f"the lab cannot render {camera!r} of task {task!r}")
    frames = _Frames(
        Camera(model_camera, "", int(params["camera_width"]), int(params["camera_height"])),
        ticks,
    )
    try:
        verdict = replay(mcap, renderers=[frames])
    except (ReplayError, LabError) as err:
        raise ExportError(f"the camera's missing images could not be rendered: {err}") from None
    if verdict.divergence is not None and verdict.divergence.tick <= max(ticks):
        raise ExportError(
            f"the camera's missing images could not be rendered: {verdict.divergence}"
        )
    log.info("rendered %d images of %s from %s", len(frames.frames), camera, mcap)
    return frames.frames


def source(mcap: Path, known: Mapping[str, Any]) -> Source:
    """A record to export, with its provenance and the lab's renderer."""

    def draw(camera: str, ticks: Sequence[int]) -> Mapping[int, bytes]:
        return render(mcap, camera, ticks)

    return Source(mcap, provenance_of(mcap, known), draw)


def export_records(
    records: Sequence[tuple[Path, Mapping[str, Any]]], out: Path, fmt: ExportFormat
) -> ExportSummary:
    """Export the records (an MCAP file and what the archive knows of it, each) to ``out``
    in the format ``fmt`` (``repository.formats``), one episode per record (more for a
    record that holds several); all of one task."""
    sources = [source(path, known) for path, known in records]
    tasks = {s.provenance.get("task") for s in sources}
    if len(tasks) != 1:
        named = ", ".join(sorted(map(str, tasks)))
        raise ExportError(f"one export holds one task's records; these are of {named}")
    return export(sources, out, fmt, layout(str(tasks.pop())))


def write_dataset(records: Sequence[tuple[Mapping[str, Any], Path]], out: Path) -> None:
    """The learning formats of a trial's pinned records (``scheduler.data``): for each
    task, a LeRobot dataset without video (the records hold the images they have) and
    ``arrays.npz``."""
    by_task: dict[str, list[Source]] = {}
    for known, path in records:
        task = str(known["task"])
        if _layout(task) is None:  # no layout: the MCAP records are the data
            log.info("no LeRobot dataset of %s: the task has no export layout", task)
            continue
        by_task.setdefault(task, []).append(Source(path, provenance_of(path, known)))
    for task, sources in sorted(by_task.items()):
        plain = dataclasses.replace(layout(task), cameras=())
        folder = out / task
        export(sources, folder, LEROBOT, plain)
        table = pq.read_table(folder / DATA_PATH.format(chunk_index=0, file_index=0))
        episodes = pq.read_table(folder / EPISODES_PATH)
        trials = np.array(episodes.column("labd/trial").to_pylist(), np.int64)
        episode = np.array(table.column("episode_index").to_pylist(), np.int64)
        np.savez(
            folder / ARRAYS,
            observation=np.array(table.column("observation.state").to_pylist(), np.float32),
            action=np.array(table.column("action").to_pylist(), np.float32),
            episode=episode,
            tick=np.array(table.column("frame_index").to_pylist(), np.int64),
            trial=trials[episode],
            reward=np.array(table.column("next.reward").to_pylist(), np.float32),
            done=np.array(table.column("next.done").to_pylist(), np.bool_),
            success=np.array(table.column("next.success").to_pylist(), np.bool_),
            observation_names=np.array([e.name for e in plain.observation]),
            action_names=np.array([e.name for e in plain.action]),
        )
