"""The trial recorder: every message of a robot's graph in one MCAP file, as a rosbag2 bag.

A ``Recorder`` (``record``) taps a ``Graph`` and writes each message delivered on any
topic, in delivery order, to ``FOLDER/trial.mcap`` in MCAP's ROS 2 profile, so that
``ros2 bag``, rosbags and Foxglove open it; ``finish`` adds the manifest and the
attachments, completes the file and writes ``FOLDER/metadata.yaml`` (``bag``), which
makes the folder a rosbag2 bag. The data digest over the observation and action stream
decides whether a rerun reproduced a trial; ``first_difference`` says where two records
part (``digest``). Each channel says which side of the bridge published on it (``lab``
or ``client``), so ``read_messages`` picks a record's observations or actions without
knowing its task (``reader``). A record's summary for its page (plots, camera
thumbnails, the maze's map, the 3D scene from the task's model it carries) is read from
it once, when the trial is filed (``summary``, with ``series`` and ``scene``).

    FOLDER/
    ├── trial.mcap       schemas (ros2msg), channels (cdr) per topic and side, messages
    │                    at simulation time, zstd chunks; metadata "manifest" and
    │                    "rosbag2"; attachments
    └── metadata.yaml    rosbag2 bag metadata, format 9, storage mcap

The modules import nothing from the rest of the lab but the graph, and the graph nothing
from them; they read MCAP files through the archive's ``repository.mcapfile``, which
bounds what a file may make a reader hold, and take the names a record shares with
the rest of the lab from ``repository.well_known`` and its manifest's canonical JSON
from ``repository.digests``.
"""

from __future__ import annotations

from labd.recorder.bag import BAG_METADATA, write_bag_metadata
from labd.recorder.digest import (
    Difference,
    Entry,
    data_digest,
    digest_topics,
    first_difference,
)
from labd.recorder.reader import (
    RecordedChannel,
    RecordedMessage,
    read_attachments,
    read_channels,
    read_messages,
)
from labd.recorder.record import Recorder, RecordSummary, read_manifest

__all__ = [
    "BAG_METADATA",
    "Difference",
    "Entry",
    "RecordSummary",
    "RecordedChannel",
    "RecordedMessage",
    "Recorder",
    "data_digest",
    "digest_topics",
    "first_difference",
    "read_attachments",
    "read_channels",
    "read_manifest",
    "read_messages",
    "write_bag_metadata",
]
